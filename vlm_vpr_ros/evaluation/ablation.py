"""The paper's ablation on one dataset: which parts of the method buy accuracy, and how top-p
matters. Pure core: works on precomputed query descriptors and prior results.

Rows (each evaluated at every top-p of the sweep):

* ``no prior (VPR only)`` — global retrieval, best descriptor match;
* ``prior + re-rank, no submap`` — global top-p, re-ranked by distance to the prior;
* ``country submap`` / ``cluster submap``, each ``no re-rank`` and ``+ re-rank`` — the prior
  picks the submap (one per country, or K-means on position), then retrieval (and re-ranking)
  happens in it;
* ``prior region + posterior`` / ``no prior, posterior vote`` — the default fusion
  (docs/fusion.md) with and without the prior.

The ``fusion`` column says which fusion mode each row runs (the paper's rows: ``paper``).

The country and cluster partitions are made in memory from the same map
(:func:`vlm_vpr_ros.mapping.assemble.repartition`), so one map and one set of descriptors serve
every row.
The prior itself (``prior only``) is reported as a reference row.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from vlm_vpr_ros.errors import DataError
from vlm_vpr_ros.evaluation.metrics import errors_km, summarize
from vlm_vpr_ros.geodesy import THRESHOLDS_KM
from vlm_vpr_ros.localization.localizer import Localizer, LocalizerConfig
from vlm_vpr_ros.maps.reference_map import ReferenceMap
from vlm_vpr_ros.mapping.assemble import repartition
from vlm_vpr_ros.priors.provider import PriorResult

log = logging.getLogger(__name__)

TOP_PS = (1, 5, 10, 25, 50, 100)
PRIOR_ONLY = "prior only (no VPR)"


@dataclass(frozen=True)
class AblationRow:
    name: str
    partition: str | None  # "country" / "kmeans" map for the submap rows, None: whole map
    use_prior: bool
    use_submaps: bool
    rerank: bool
    fusion: str = "paper"  # LocalizerConfig.fusion: "paper" or "posterior"


ROWS = (
    AblationRow("no prior (VPR only)", None, False, False, False),
    AblationRow("prior + re-rank, no submap", None, True, False, True),
    AblationRow("country submap, no re-rank", "country", True, True, False),
    AblationRow("country submap + re-rank", "country", True, True, True),
    AblationRow("cluster submap, no re-rank", "kmeans", True, True, False),
    AblationRow("cluster submap + re-rank", "kmeans", True, True, True),
    AblationRow("prior region + posterior", None, True, True, True, "posterior"),
    AblationRow("no prior, posterior vote", None, False, True, True, "posterior"),
)


@dataclass
class AblationResult:
    top_ps: list[int]
    #: row name → one summary ({"n", "accuracy", "median_km"}) per top-p
    rows: dict[str, list[dict]] = field(default_factory=dict)
    prior_only: dict | None = None
    clusters: int = 0
    n_submaps: dict[str, int] = field(default_factory=dict)
    #: row name → fusion mode ("paper" / "posterior")
    fusion: dict[str, str] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return {"top_p": self.top_ps, "rows": self.rows, "prior_only": self.prior_only,
                "kmeans_clusters": self.clusters, "n_submaps": self.n_submaps,
                "fusion": self.fusion}


def run_ablation(ref_map: ReferenceMap, descriptors: np.ndarray, truth: np.ndarray,
                 priors: Sequence[PriorResult | None], top_ps: Sequence[int] = TOP_PS,
                 clusters: int | None = None, rows: Sequence[AblationRow] = ROWS,
                 progress: Callable[[str], None] | None = None) -> AblationResult:
    """Localize every query under every row × top-p and summarize the errors.

    ``descriptors`` (N, D) match ``truth`` (N, 2) lat/lon and ``priors`` (N) row by row; a
    ``None`` or failed prior makes that query fall back to global retrieval (as on a robot).
    ``clusters``: K of the cluster partition (default: the map's own K when it is a K-means
    map, else 100; clamped to the data)."""
    desc = np.asarray(descriptors, dtype=np.float32)
    truth = np.asarray(truth, dtype=np.float64).reshape(-1, 2)
    if not (len(desc) == len(truth) == len(priors)) or len(desc) == 0:
        raise DataError(f"ablation needs matching non-empty inputs: {len(desc)} descriptors, "
                        f"{len(truth)} ground-truth rows, {len(priors)} priors")
    ps = sorted({int(p) for p in top_ps})
    if not ps or ps[0] < 1:
        raise DataError(f"top-p values must be >= 1, got {list(top_ps)}")
    params = ref_map.manifest.get("partition", {}).get("params", {})
    own_k = params.get("clusters") if ref_map.partition_method == "kmeans" else None
    if clusters is None:
        clusters = int(own_k or 100)
    maps = {None: ref_map}
    for part in sorted({r.partition for r in rows if r.partition}):
        same = part == ref_map.partition_method and (part == "country" or own_k == clusters)
        maps[part] = ref_map if same else repartition(ref_map, part, clusters=clusters)
    result = AblationResult(ps, clusters=clusters,
                            n_submaps={str(k): len(m.submaps) for k, m in maps.items() if k})
    gt = [tuple(g) for g in truth]
    for row in rows:
        result.rows[row.name] = []
        result.fusion[row.name] = row.fusion
        for p in ps:
            if progress:
                progress(f"{row.name}, top-p {p}")
            loc = Localizer(maps[row.partition], LocalizerConfig(
                top_p=p, use_submaps=row.use_submaps, rerank=row.rerank, fusion=row.fusion))
            est = []
            for d, pr in zip(desc, priors):
                hyp = loc.localize(d, pr if row.use_prior else None)
                est.append((hyp.lat, hyp.lon))
            result.rows[row.name].append(summarize(errors_km(est, gt)))
    prior_est = [(pr.prior.lat, pr.prior.lon) if pr is not None and pr.prior is not None
                 else None for pr in priors]
    result.prior_only = summarize(errors_km(prior_est, gt))
    return result


def ablation_table(result: AblationResult,
                   table_top_p: int | None = None) -> tuple[str, int, dict[str, dict]]:
    """(title, top-p, rows) of the paper-style table at one top-p (default: the largest
    swept); each row name starts with its fusion mode."""
    ps = result.top_ps
    p = table_top_p if table_top_p in ps else ps[-1]
    i = ps.index(p)
    table = {_label(result, name): sums[i] for name, sums in result.rows.items()}
    if result.prior_only is not None:
        table = {f"{'-':<10}{PRIOR_ONLY}": result.prior_only, **table}
    n = next(iter(table.values()))["n"]
    title = (f"Ablation at top-p = {p} ({n} queries; cluster submaps: "
             f"K={result.n_submaps.get('kmeans', result.clusters)}, "
             f"countries: {result.n_submaps.get('country', '-')})")
    return title, p, table


def _label(result: AblationResult, name: str) -> str:  # the fusion mode as the first column
    return f"{result.fusion.get(name, 'paper'):<10}{name}"


def format_ablation(result: AblationResult, table_top_p: int | None = None,
                    sweep_metric: str = "25km") -> str:
    """The paper-style table at one top-p (default: the largest swept), then the top-p sweep
    of one threshold."""
    from vlm_vpr_ros.evaluation.metrics import format_table

    ps = result.top_ps
    title, _, table = ablation_table(result, table_top_p)
    out = [format_table(table, title=title)]
    keys = [f"{t:g}km" for t in THRESHOLDS_KM]
    if sweep_metric not in keys:
        raise DataError(f"unknown metric {sweep_metric!r}; choices: {', '.join(keys)}")
    head = f"{'fusion':<10}{'accuracy @ ' + sweep_metric[:-2] + ' km vs top-p':<36}" + "".join(
        f"{'p=' + str(q):>9}" for q in ps)
    out += ["", head, "-" * len(head)]
    for name, sums in result.rows.items():
        out.append(f"{_label(result, name):<46}" + "".join(f"{s['accuracy'][sweep_metric]:>8.2f}%"
                                           for s in sums))
    return "\n".join(out)
