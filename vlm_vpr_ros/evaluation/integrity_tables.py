"""The integrity report as tables: the printed two-column report (``vlm-vpr evaluate``,
``evaluate-bag``, the soak) and the one-row-per-run summary of the demo and the docs
(:mod:`vlm_vpr_ros.evaluation.integrity` computes the numbers)."""

from __future__ import annotations

import os

from vlm_vpr_ros.evaluation.integrity import (DEFAULT_ALERT_LIMIT_M, REGIONS, integrity_report,
                                              read_trials, write_report)
from vlm_vpr_ros.evaluation.metrics import read_ground_truth


def _pct(x: float | None) -> str:
    return "-" if x is None else f"{100.0 * x:.2f}%"


def report_rows(rep: dict) -> list[list[str]]:
    """``[measure, value]`` rows of the report (the printed table and the docs table)."""
    al, pl = rep["alert_limit_m"], rep["protection_level"]
    acc, sc, reg = rep["accuracy_m"], rep["scenes"], rep["regions"]
    fmt = (lambda x: "-" if x is None else f"{x:.1f} m")  # noqa: E731
    avail = rep["availability_pct"]
    rows = [["answers / fixes", f"{rep['answers']} / {rep['fixes']}"],
            ["availability (fixes / answers)", "-" if avail is None else f"{avail:.1f}%"],
            ["accuracy of fixes: 50 % / 95 % / max",
             f"{fmt(acc['p50'])} / {fmt(acc['p95'])} / {fmt(acc['max'])}"]]
    if pl["available"]:
        rows += [["protection level of fixes: median", fmt(pl["median_m"])],
                 [f"regions (AL {al:g} m): nominal / MI / HMI / unavailable",
                  " / ".join(str(reg[k]) for k in REGIONS)]]
        if rep["fixes_pl_at_or_above_al"]:
            rows.append([f"  of them fixes with PL >= {al:g} m (FIX, yet unavailable)",
                         str(rep["fixes_pl_at_or_above_al"])])
        if reg["no_pl"] or pl["invalid_values"]:
            rows.append(["fixes without a usable PL (junk PL values)",
                         f"{reg['no_pl']} ({pl['invalid_values']})"])
        rows += [["HMI (DO-229: error > AL while PL < AL), per fix",
                  f"{rep['hmi']['count']} ({_pct(rep['hmi']['per_fix'])})"],
                 ["error > PL while FIX (issue 27 HMI), per fix",
                  f"{rep['error_gt_pl']['count']} ({_pct(rep['error_gt_pl']['per_fix'])})"]]
    else:
        why = ("no protection_m column" if pl["column"] is False else
               f"no usable value; {pl['invalid_values']} junk" if pl["invalid_values"] else
               "no value")
        rows.append(["protection level", f"not available ({why})"])
    rows.append([f"fixes > {al:g} m off, per fix",
                 f"{rep['error_gt_al']['count']} ({_pct(rep['error_gt_al']['per_fix'])})"])
    per = ("HMI / error > PL / > AL" if pl["available"] else f"fixes > {al:g} m off")
    vals = ([sc["hmi"]["count"], sc["error_gt_pl"]["count"], sc["error_gt_al"]["count"]]
            if pl["available"] else [sc["error_gt_al"]["count"]])
    rows.append([f"distinct scenes ({sc['source']}): n / with fix",
                 f"{sc['n']} / {sc['with_fix']}"])
    rows.append([f"scenes with {per}", " / ".join(map(str, vals))])
    ts = rep.get("time")
    if ts is not None:
        rows += [["time to first fix", fmt_s(ts["ttff_s"])],
                 ["longest gap between fixes / without a fix",
                  f"{fmt_s(ts['longest_gap_s'])} / {fmt_s(ts['longest_outage_s'])}"]]
    return rows


def fmt_s(x: float | None) -> str:
    return "-" if x is None else f"{x:.1f} s"


def format_report(rep: dict, title: str = "integrity") -> str:
    """The report as a two-column plain-text table."""
    rows = report_rows(rep)
    w = max(len(r[0]) for r in rows) + 2
    return "\n".join([title, "-" * (w + 24)] + [f"{m:<{w}}{v}" for m, v in rows])


#: columns of the summary table (demo, docs): one row per run
TABLE_COLUMNS = ["", "answers", "fixes", "avail.", "fix err 50%", "fix err 95%", "PL median",
                 "nominal", "MI", "HMI", "unavail.", "err > PL", "fix > AL", "HMI scenes"]


def summary_cells(reports: dict[str, dict]) -> tuple[list[str], list[list[str]]]:
    """Header and rows (strings) of a one-row-per-run integrity table (``-``: not available)."""
    def m(x: float | None) -> str:
        return "-" if x is None else f"{x:.1f} m"

    body = []
    for name, r in reports.items():
        pl, reg = r["protection_level"]["available"], r["regions"]
        avail = r["availability_pct"]
        cells = [name, str(r["answers"]), str(r["fixes"]),
                 "-" if avail is None else f"{avail:.1f}%", m(r["accuracy_m"]["p50"]),
                 m(r["accuracy_m"]["p95"]), m(r["protection_level"]["median_m"])]
        cells += ([str(reg[k]) for k in REGIONS] + [str(r["error_gt_pl"]["count"])] if pl
                  else ["-"] * 5)
        cells += [str(r["error_gt_al"]["count"]),
                  str(r["scenes"]["hmi"]["count"]) if pl else "-"]
        body.append(cells)
    return list(TABLE_COLUMNS), body


def demo_integrity(out_dir: str | os.PathLike[str], truth_csv: str | os.PathLike[str],
                   runs: dict[str, str | os.PathLike[str]],
                   alert_limit_m: float = DEFAULT_ALERT_LIMIT_M) -> dict:
    """The demo's integrity step: a report per verified run (``label -> results CSV``), the
    summary table and the first run's Stanford diagram in ``out_dir`` (replaced on re-runs)."""
    truth = read_ground_truth(truth_csv)
    reports, first = {}, None
    for label, path in runs.items():
        trials, info = read_trials(path, truth)
        reports[label] = integrity_report(trials, alert_limit_m, pl_column=info["pl_column"],
                                          pl_invalid=info["pl_invalid"])
        first = first or (label, trials)
    head, body = summary_cells(reports)
    outputs = {}
    if first is not None:
        outputs = write_report(out_dir, reports[first[0]], first[1], f"demo: {first[0]}",
                               overwrite=True)
    return {"alert_limit_m": alert_limit_m, "reports": reports, "outputs": outputs,
            "table": {"title": f"Integrity of the verified runs (alert limit "
                               f"{alert_limit_m:g} m; docs/evaluation.md)",
                      "columns": head, "rows": body}}
