"""Fault-injection suite helpers: in-process CLI runs, file snapshots, the catalogue count."""

from __future__ import annotations

import hashlib
import logging
import shutil
from pathlib import Path

import pytest

def sha_tree(*paths: Path) -> dict[str, str]:
    """sha256 of every file under ``paths`` (the user's data, hashed before and after)."""
    out = {}
    for root in paths:
        root = Path(root)
        files = [root] if root.is_file() else sorted(p for p in root.rglob("*") if p.is_file())
        for p in files:
            out[str(p)] = hashlib.sha256(p.read_bytes()).hexdigest()
    return out


class Cli:
    """Run ``vlm-vpr`` in-process; return code, stdout and the ERROR lines logged."""

    def __init__(self, capsys, caplog) -> None:
        self.capsys, self.caplog = capsys, caplog

    def __call__(self, *args) -> tuple[int, str, list[str]]:
        from vlm_vpr_ros.cli import main

        self.caplog.clear()
        with self.caplog.at_level(logging.INFO):
            rc = main([str(a) for a in args])
        out = self.capsys.readouterr()
        errors = [r.getMessage() for r in self.caplog.records if r.levelno >= logging.ERROR]
        self.text = out.out + out.err + "\n".join(r.getMessage() for r in self.caplog.records)
        return rc, out.out, errors


@pytest.fixture
def cli(capsys, caplog) -> Cli:
    return Cli(capsys, caplog)


def exit2(result, *needles: str) -> str:
    """Assert exit 2 with exactly one one-line error naming ``needles``; return it."""
    rc, _, errors = result
    assert rc == 2, (rc, errors)
    assert len(errors) == 1 and "\n" not in errors[0], errors
    assert "Traceback" not in errors[0]
    for n in needles:
        assert n in errors[0], (n, errors[0])
    return errors[0]


@pytest.fixture
def map_copy(demo_map, tmp_path) -> Path:
    """A private copy of the shared demo map (vlad_rootsift_fast, 8 k-means submaps)."""
    dst = tmp_path / "map"
    shutil.copytree(demo_map, dst)
    return dst


@pytest.fixture
def queries(demo_data, tmp_path) -> Path:
    """A queries CSV of 6 demo images."""
    names = sorted(p.name for p in (demo_data / "images").iterdir())[:6]
    q = tmp_path / "queries.csv"
    q.write_text("file\n" + "\n".join(names) + "\n")
    return q


def copy_refs(demo_data: Path, folder: Path, n: int) -> list[tuple[str, float, float]]:
    """``n`` demo images copied into ``folder`` as ``new_<k>.jpg`` (references a map of the
    demo images does not hold); returns their (file, lat, lon) rows."""
    folder.mkdir(parents=True, exist_ok=True)
    rows = []
    for k, line in enumerate((demo_data / "coords.csv").read_text().splitlines()[1:n + 1]):
        f, lat, lon = line.split(",")[:3]
        shutil.copy(demo_data / "images" / f, folder / f"new_{k}.jpg")
        rows.append((f"new_{k}.jpg", float(lat), float(lon)))
    return rows
