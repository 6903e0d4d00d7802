"""A query that asks for another verification preset than the map's is refused, naming both
(issue 42): a learned matcher on a map whose features and p_correct are SIFT's would give a
calibration that does not apply."""

from __future__ import annotations

import pytest
from demo_subset import demo_coords

from vlm_vpr_ros.errors import ConfigError
from vlm_vpr_ros.localization.verification.stage import Verifier
from vlm_vpr_ros.maps.reference_map import ReferenceMap


@pytest.fixture(scope="module")
def sift_map(demo_data, tmp_path_factory):
    from vlm_vpr_ros.mapping.build_images import build_map

    tmp = tmp_path_factory.mktemp("sift_preset")
    rows, coords = demo_coords(demo_data, tmp, 6)
    out = tmp / "map"
    build_map(demo_data / "images", coords, out, descriptor="vlad_rootsift_fast",
              partition="none", progress=False, calibration_conditions="full")
    return ReferenceMap.load(out)


def test_another_preset_is_refused_naming_both(sift_map):
    with pytest.raises(ConfigError, match="'xfeat_mnn' cannot use this map.*preset 'sift'"):
        Verifier(sift_map, {"top_k": 20, "preset": "xfeat_mnn"})
    with pytest.raises(ConfigError, match="unknown verification preset 'orb'"):
        Verifier(sift_map, {"top_k": 20, "preset": "orb"})


def test_the_maps_own_preset_verifies(sift_map):
    for preset in ("", "sift"):
        v = Verifier(sift_map, {"top_k": 20, "preset": preset})
        assert v.enabled and v.preset.name == "sift" and v.model.calibrated


def test_cli_refuses_with_one_line(sift_map, demo_data, tmp_path, caplog):
    from vlm_vpr_ros.cli import main

    queries = tmp_path / "q.csv"
    queries.write_text("file\n" + sorted(p.name for p in (demo_data / "images").iterdir())[0]
                       + "\n")
    rc = main(["localize", "--map", str(sift_map.path), "--images", str(demo_data / "images"),
               "--queries", str(queries), "--out", str(tmp_path / "r.csv"),
               "--verify-preset", "disk_lightglue"])
    errors = [r.getMessage() for r in caplog.records if r.levelname == "ERROR"]
    assert rc == 2 and not (tmp_path / "r.csv").exists()
    assert len(errors) == 1 and "'disk_lightglue'" in errors[0] and "'sift'" in errors[0]
