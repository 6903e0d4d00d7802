"""Shared fixtures: the shipped demo data, a small demo map, and ../shared (skipped if absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
DEMO_DATA = REPO / "vlm_vpr_ros" / "data" / "osv5m_demo"
SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))


@pytest.fixture(scope="session")
def demo_data() -> Path:
    """The shipped demo folder: images/, coords.csv, priors_osv5m_baseline.csv."""
    return DEMO_DATA


@pytest.fixture(scope="session")
def shared_dir() -> Path:
    """``../shared`` next to the clone (real data by others); tests skip when it is absent."""
    if not (SHARED / "data").is_dir():
        pytest.skip("../shared is absent (real-data checks only run in the project workspace)")
    return SHARED


@pytest.fixture(scope="session")
def demo_map(tmp_path_factory, demo_data) -> Path:
    """A map of the 71 shipped demo images: vlad_rootsift_fast, kmeans partition (K=8)."""
    from vlm_vpr_ros.map_build import build_map

    out = tmp_path_factory.mktemp("demo_map") / "map"
    build_map(demo_data / "images", demo_data / "coords.csv", out,
              descriptor="vlad_rootsift_fast", partition="kmeans", clusters=8, progress=False)
    return out


@pytest.fixture(scope="session")
def demo_country_map(tmp_path_factory, demo_data) -> Path:
    """The same images with one submap per country."""
    from vlm_vpr_ros.map_build import build_map

    out = tmp_path_factory.mktemp("demo_country_map") / "map"
    build_map(demo_data / "images", demo_data / "coords.csv", out,
              descriptor="vlad_rootsift_fast", partition="country", progress=False)
    return out
