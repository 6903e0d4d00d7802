"""Real retrieval check on ../shared/data/sf_night (332 database + 34 night queries, most from
another date than their match); skipped when ../shared is absent. README reports the figure."""

import pytest

from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.imageio import load_image
from vlm_vpr_ros.map_build import build_map, read_coords_csv
from vlm_vpr_ros.pipeline import LocalizationPipeline


@pytest.fixture(scope="module")
def sf(shared_dir, tmp_path_factory):
    root = shared_dir / "data" / "sf_night"
    out = tmp_path_factory.mktemp("sf") / "map"
    build_map(root, root / "database.csv", out, partition="kmeans", clusters=10,
              progress=False)
    return root, out


def test_sf_night_recall_within_25m(sf):
    root, map_dir = sf
    pipe = LocalizationPipeline.open(map_dir, localizer={"top_p": 5})
    queries = read_coords_csv(root / "queries.csv")
    assert len(queries) == 34
    r1 = r5 = 0
    for f, lat, lon in queries:
        hyp = pipe.localize_image(load_image(root / f), None)
        d_m = [haversine_km(lat, lon, c.lat, c.lon) * 1000 for c in hyp.candidates[:5]]
        r1 += d_m[0] <= 25
        r5 += min(d_m) <= 25
    recall1, recall5 = 100 * r1 / 34, 100 * r5 / 34
    print(f"sf_night vlad_rootsift: Recall@1 {recall1:.1f}%  Recall@5 {recall5:.1f}% (25 m)")
    # measured 50.0 / 55.9 on this machine; a broken descriptor gives ~0 (chance is < 2 %)
    assert recall1 >= 40.0 and recall5 >= 50.0


def test_sf_night_prior_restricts_to_submap(sf):
    root, map_dir = sf
    from vlm_vpr_ros.priors.base import Prior, PriorResult

    pipe = LocalizationPipeline.open(map_dir, localizer={"fusion": "paper"})
    f, lat, lon = read_coords_csv(root / "queries.csv")[0]
    hyp = pipe.localize_image(load_image(root / f), PriorResult(Prior(lat, lon, "gt"), "gt"))
    sub = pipe.map.submaps[pipe.map.submap_index(hyp.submap)]
    assert {c.ref_id for c in hyp.candidates} <= set(sub.ids)
    assert haversine_km(lat, lon, hyp.lat, hyp.lon) < 5.0  # same city district at worst
