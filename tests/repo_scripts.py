"""The repository's scripts and benchmarks as modules, for the tests that call their functions
(they are files, not a package): ``load("scripts/gen_docs.py")``."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

REPO = Path(__file__).resolve().parents[1]


def load(rel: str) -> ModuleType:
    """The file ``rel`` (relative to the repository) run as a module named after it, registered
    in ``sys.modules`` (dataclasses and pickling look their module up there)."""
    path = REPO / rel
    spec = importlib.util.spec_from_file_location(path.stem, path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = mod
    spec.loader.exec_module(mod)
    return mod
