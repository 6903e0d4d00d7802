"""The ablation runner against brute-force references computed here with numpy."""

from __future__ import annotations

import json

import numpy as np
import pytest

from vlm_vpr_ros.evaluation.ablation import PRIOR_ONLY, ROWS, format_ablation, run_ablation
from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.evaluation.metrics import errors_km, summarize
from vlm_vpr_ros.geodesy import haversine_km
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.priors.provider import Prior, PriorResult
from vlm_vpr_ros.priors.simple import read_prior_csv

TOP_PS = (1, 5, 25, 100)


@pytest.fixture(scope="module")
def setup(demo_map, demo_data):
    """Queries = the map's own descriptors plus noise; truth = the references' positions;
    priors = the OSV-5M baseline's recorded guesses (a few replaced by failures)."""
    m = ReferenceMap.load(demo_map)
    desc = m.all_descriptors()
    rng = np.random.default_rng(7)
    q = desc + rng.normal(0, 0.6 * desc.std(), desc.shape).astype(np.float32)
    truth = m.all_coords()
    table = read_prior_csv(demo_data / "priors_osv5m_baseline.csv")
    priors = [PriorResult(Prior(*table[i], "recorded"), "recorded") for i in m.all_ids()]
    priors[3] = PriorResult.failure("recorded", "timeout")
    priors[10] = None
    res = run_ablation(m, q, truth, priors, TOP_PS)
    return m, desc, q, truth, priors, res


def _summary(est, truth):
    return summarize(errors_km(est, [tuple(t) for t in truth]))


def test_no_prior_row_is_brute_force_nearest_neighbour(setup):
    m, desc, q, truth, priors, res = setup
    d2 = ((q[:, None, :] - desc[None, :, :]) ** 2).sum(-1)
    nn = d2.argmin(1)
    ref = _summary([tuple(truth[j]) for j in nn], truth)
    assert res.rows["no prior (VPR only)"] == [ref] * len(TOP_PS)


def test_prior_rerank_without_submap(setup):
    """Global top-p by squared L2, then the candidate nearest to the prior; a failed prior falls
    back to the best descriptor match."""
    m, desc, q, truth, priors, res = setup
    d2 = ((q[:, None, :] - desc[None, :, :]) ** 2).sum(-1)
    for k, p in enumerate(TOP_PS):
        est = []
        for i in range(len(q)):
            top = np.argsort(d2[i], kind="stable")[:p]
            pr = priors[i]
            if pr is None or pr.prior is None:
                j = top[0]
            else:
                dk = haversine_km(pr.prior.lat, pr.prior.lon, truth[top, 0], truth[top, 1])
                j = top[int(np.argmin(dk))]
            est.append(tuple(truth[j]))
        assert res.rows["prior + re-rank, no submap"][k] == _summary(est, truth), p


def test_rows_structure_and_invariants(setup, demo_data):
    m, desc, q, truth, priors, res = setup
    assert list(res.rows) == [r.name for r in ROWS]
    assert all(len(v) == len(TOP_PS) for v in res.rows.values())
    for part in ("country", "cluster"):  # at top-p 1 re-ranking has nothing to choose from
        assert res.rows[f"{part} submap, no re-rank"][0] == res.rows[f"{part} submap + re-rank"][0]
        # without re-ranking, top-p does not change the answer
        assert len({json.dumps(s) for s in res.rows[f"{part} submap, no re-rank"]}) == 1
    ccs = {line.split(",")[-1] for line in
           (demo_data / "coords.csv").read_text().splitlines()[1:]}
    assert res.n_submaps["country"] == len(ccs) == 48
    assert res.n_submaps["kmeans"] == 8  # the demo map's own K
    est = [None if p is None or p.prior is None else (p.prior.lat, p.prior.lon) for p in priors]
    assert res.prior_only == _summary(est, truth)


def test_other_k_and_table(setup):
    m, desc, q, truth, priors, _ = setup
    res = run_ablation(m, q, truth, priors, (1, 10), clusters=4)
    assert res.n_submaps["kmeans"] == 4 and res.top_ps == [1, 10]
    text = format_ablation(res, table_top_p=10, sweep_metric="200km")
    assert "Ablation at top-p = 10" in text and PRIOR_ONLY in text
    assert "accuracy @ 200 km vs top-p" in text and "p=10" in text
    assert all(r.name in text for r in ROWS)
    with pytest.raises(DataError, match="choices: 1km"):
        format_ablation(res, sweep_metric="3km")


def test_bad_inputs(setup):
    m, desc, q, truth, priors, _ = setup
    with pytest.raises(DataError, match="matching"):
        run_ablation(m, q[:5], truth, priors)
    with pytest.raises(DataError, match=">= 1"):
        run_ablation(m, q, truth, priors, top_ps=(0, 5))


def test_cli_ablate(demo_map, demo_data, tmp_path, capsys):
    from vlm_vpr_ros.cli import main

    lines = (demo_data / "coords.csv").read_text().splitlines()[:16]
    (tmp_path / "q.csv").write_text("\n".join(lines) + "\n")
    rc = main(["ablate", "--map", str(demo_map), "--images", str(demo_data / "images"),
               "--queries", str(tmp_path / "q.csv"), "--priors",
               str(demo_data / "priors_osv5m_baseline.csv"), "--top-p", "1,5,50",
               "--out", str(tmp_path / "abl"), "--json"])
    assert rc == 0
    out = json.loads(capsys.readouterr().out)
    assert out["top_p"] == [1, 5, 50] and out["prior_only"]["n"] == 15
    assert (tmp_path / "abl" / "ablation_top_p.png").read_bytes()[:4] == b"\x89PNG"
    assert json.loads((tmp_path / "abl" / "ablation.json").read_text()) == out
    assert main(["ablate", "--map", str(demo_map), "--top-p", "1,x"]) == 2
