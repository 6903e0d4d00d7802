"""Every numeric command-line option checked once, before a command starts: finite and in
range, or exit 2 with one line naming the option (``--prior-timeout inf`` would otherwise be
an OverflowError on every query, ``--clusters 0`` a silent clamp, ``--prior-timeout -1`` a VLM
never waited for).

The rules are keyed by the option's destination name, so an option shared by several commands
(``--prior-timeout``, ``--top-p``) is checked the same way everywhere, and a new command that
reuses a name is covered. Values argparse did not parse as numbers (``ablate --top-p 1,5,10``
is a list) are left to their command.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass

from vlm_vpr_ros.errors import ConfigError


@dataclass(frozen=True)
class Rule:
    """A number in [lo, hi] (``open_lo``: lo excluded); ``integer``: an int."""

    lo: float
    hi: float
    integer: bool = False
    open_lo: bool = False
    unit: str = ""

    def check(self, flag: str, value: int | float) -> None:
        ok = math.isfinite(value) and (value > self.lo if self.open_lo else value >= self.lo) \
            and value <= self.hi
        if not ok:
            kind = "an integer" if self.integer else "a finite number"
            lo = f"> {_num(self.lo)}" if self.open_lo else f">= {_num(self.lo)}"
            raise ConfigError(f"{flag} must be {kind}{' of ' + self.unit if self.unit else ''}"
                              f" {lo} and <= {_num(self.hi)}, got {value!r}")


def _num(x: float) -> str:
    return f"{int(x):,}" if float(x).is_integer() else f"{x:g}"


DAY_S = 86400.0
RULES: dict[str, Rule] = {
    # priors and the localizer (localize, evaluate-bag, ablate, priors ...)
    "prior_timeout": Rule(0, DAY_S, open_lo=True, unit="seconds"),
    "top_p": Rule(1, 100_000, integer=True),
    "n_submaps": Rule(1, 1_000_000, integer=True),
    # map building
    "clusters": Rule(1, 1_000_000, integer=True),
    "max_submap_size": Rule(1, 10 ** 12, integer=True),
    "rerank_factor": Rule(1, 10_000, integer=True),
    "ram_budget_mb": Rule(0, 10 ** 9, open_lo=True, unit="MB"),
    # teach runs (build-map --bag, map add --bag)
    "fix_tolerance_s": Rule(0, DAY_S, open_lo=True, unit="seconds"),
    "min_spacing_m": Rule(0, 1e7, unit="metres"),
    "max_fix_sigma_m": Rule(0, 1e7, open_lo=True, unit="metres"),
    # bags
    "rate": Rule(0, 1e6, open_lo=True),
    "wait_subscribers": Rule(0, DAY_S, unit="seconds"),
    "clock": Rule(0, 1e4, open_lo=True, unit="Hz"),
    "domain_id": Rule(0, 232, integer=True),
    "max_gt_gap": Rule(0, DAY_S, unit="seconds"),
    "max_frames": Rule(1, 10 ** 12, integer=True),
    "table_top_p": Rule(1, 100_000, integer=True),
    # describe / --engine ray
    "workers": Rule(1, 100_000, integer=True),
    "batch_size": Rule(1, 4096, integer=True),
    "num_gpus_per_worker": Rule(0, 64),
    "shard_size": Rule(1, 10 ** 9, integer=True),
}


def check_args(args: argparse.Namespace) -> None:
    """ConfigError (one line naming the option) for the first numeric option out of range."""
    for dest, rule in RULES.items():
        value = getattr(args, dest, None)
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            continue  # not given (None), or not a number option of this command
        rule.check("--" + dest.replace("_", "-"), value)
