"""A private copy of a map built with ``build-map --images`` and of its pictures, the map's
``source_images`` record pointing at that copy (tests that change or remove pictures)."""

from __future__ import annotations

import csv
import json
import shutil
from pathlib import Path
from typing import Any


def copy_with_pictures(pictures: Path, map_dir: Path, tmp_path: Path) -> tuple[Path, Path, dict]:
    """(pictures copy, map copy, its manifest) under ``tmp_path``."""
    pics, mp = tmp_path / "pictures", tmp_path / "map"
    shutil.copytree(pictures, pics)
    shutil.copytree(map_dir, mp)
    man = json.loads((mp / "manifest.json").read_text())
    man["source_images"]["folder"] = str(pics)
    (mp / "manifest.json").write_text(json.dumps(man))
    return pics, mp, man


def build_from_demo(demo_data: Path, work: Path, n: int, **options: Any
                    ) -> tuple[Path, Path, list[str]]:
    """(pictures folder, map, ids): a small map built with ``build_map`` (``--images``, the
    fast VLAD descriptor at 320 px, 2 clusters, ``options`` added) from a copy of the first
    ``n`` demo pictures in ``work``."""
    from vlm_vpr_ros.mapping.build_images import build_map

    rows = list(csv.DictReader(open(demo_data / "coords.csv")))[:n]
    pics = work / "pictures"
    pics.mkdir()
    for r in rows:
        shutil.copy2(demo_data / "images" / r["file"], pics / r["file"])
    coords = work / "coords.csv"
    coords.write_text("file,lat,lon\n" + "".join(f"{r['file']},{r['lat']},{r['lon']}\n"
                                                 for r in rows))
    build_map(pics, coords, work / "map", descriptor="vlad_rootsift_fast",
              descriptor_config={"max_side": 320}, clusters=2, progress=False, **options)
    return pics, work / "map", [r["file"] for r in rows]
