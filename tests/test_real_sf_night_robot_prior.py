"""The robot's own estimate as a trusted prior on real data (../shared/data/sf_night, skipped
without it), offline through ``vlm-vpr localize --prior recorded`` with a ``sigma_m`` column
(benchmarks/robot_prior_sf_night.py): an honest prior (truth moved 100 m, sigma_m 100) gives
more fixes than no prior, none more than 50 m off; a prior that lies about its sigma (truth
moved 2 km, still claiming 100 m) creates no wrong fix. ``VLM_VPR_SF_MAP`` may name a map
built from the same data (kmeans, 10 clusters) to skip the build."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.timeout(3000)


def test_robot_prior_fixes_and_the_guard_against_a_lying_sigma(sf_night_map, tmp_path):
    sys.path.insert(0, str(REPO / "benchmarks"))
    from robot_prior_sf_night import run

    data, map_dir = sf_night_map
    res = run(data, map_dir, tmp_path / "work")
    print(f"\nSF night robot prior: {res}")
    none, honest, lying = res["none"], res["honest"], res["lying"]
    assert none["off_50m"] == honest["off_50m"] == lying["off_50m"] == 0
    # the target of issue 29 is >= 15; measured 14 (docs/node.md): the honest prior must add
    # fixes to today's no-prior figure, never wrong ones
    assert honest["fixes"] >= none["fixes"] + 4
    assert lying["fixes"] <= none["fixes"]
