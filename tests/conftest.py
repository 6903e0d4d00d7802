"""Shared fixtures: the shipped demo data, a small demo map, and ../shared (skipped if absent)."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

from faults.catalogue import CATALOGUE

REPO = Path(__file__).resolve().parents[1]
DEMO_DATA = REPO / "vlm_vpr_ros" / "data" / "osv5m_demo"
SHARED = Path(os.environ.get("VLM_VPR_SHARED", REPO.parent / "shared"))

#: fault-catalogue results (tests/faults/catalogue.py): counted here, at the root, so a case
#: whose test lives beside the code it covers counts like those in tests/faults
_results: dict[str, str] = {}


def pytest_configure(config) -> None:
    config.addinivalue_line("markers", "fault(id): a fault-catalogue case (tests/faults)")


#: the longest test files (--durations), started first: with two workers (scripts/run_tests.sh,
#: --dist loadfile) a long file that starts last would run on alone at the end
LONGEST_FIRST = ("test_real_sf_night.py", "test_demo.py", "test_cpu_paths.py",
                 "test_ray_build.py", "test_weights_loading.py", "test_verification_learned.py",
                 "test_teach.py", "test_map_io.py", "test_cli_core.py")


def pytest_collection_modifyitems(items) -> None:
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order kept


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    mark = item.get_closest_marker("fault")
    if mark is not None:  # carried to the controller with the report (pytest-xdist)
        rep.user_properties.append(("fault", mark.args[0]))


def pytest_runtest_logreport(report) -> None:
    case = dict(report.user_properties).get("fault")
    if case is not None and (report.when == "call" or report.failed or report.skipped):
        if _results.get(case) in (None, "passed"):
            _results[case] = report.outcome


def pytest_terminal_summary(terminalreporter) -> None:
    if not _results:
        return
    failed = sorted(k for k, v in _results.items() if v == "failed")
    terminalreporter.write_line(
        f"fault suite: {len(_results)} of {len(CATALOGUE)} cases tried, "
        f"{len(failed)} failed (crash / data lost / secret leaked): {failed or 'none'}")


@pytest.fixture
def map_loads(monkeypatch) -> list[str]:
    """The maps a command opened (ReferenceMap.load), in order: checks that must come before
    the map is loaded assert it stays empty."""
    from vlm_vpr_ros.maps.reference_map import ReferenceMap

    calls: list[str] = []
    load = ReferenceMap.load.__func__

    def spy(cls, path, *a, **k):
        calls.append(str(path))
        return load(cls, path, *a, **k)

    monkeypatch.setattr(ReferenceMap, "load", classmethod(spy))
    return calls


@pytest.fixture(scope="module")
def one_torch_thread():
    """torch on one thread while a module runs (``pytestmark = pytest.mark.usefixtures(...)``):
    its OpenMP threads spin while they wait, which on a loaded 2-core host made each model call
    ~10x slower (bench_learned.py)."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


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
def sf_night_map(shared_dir, tmp_path_factory) -> tuple[Path, Path]:
    """(``../shared/data/sf_night``, a map of its 332 references: kmeans, 10 clusters, the
    default verification calibration), built once per test process; ``VLM_VPR_SF_MAP`` may
    name such a map to skip the build."""
    from vlm_vpr_ros.mapping.build_images import build_map

    root = shared_dir / "data" / "sf_night"
    given = os.environ.get("VLM_VPR_SF_MAP")
    if given:
        return root, Path(given)
    out = tmp_path_factory.mktemp("sf") / "map"
    build_map(root, root / "database.csv", out, partition="kmeans", clusters=10,
              progress=False)
    return root, out


@pytest.fixture(scope="session")
def demo_map(tmp_path_factory, demo_data) -> Path:
    """A map of the 71 shipped demo images: vlad_rootsift_fast, kmeans partition (K=8)."""
    from vlm_vpr_ros.mapping.build_images import build_map

    out = tmp_path_factory.mktemp("demo_map") / "map"
    build_map(demo_data / "images", demo_data / "coords.csv", out,
              descriptor="vlad_rootsift_fast", partition="kmeans", clusters=8, progress=False)
    return out


@pytest.fixture(scope="module")
def pipeline(demo_map):
    """The demo map opened as the node opens it (the runtime, relocalize and debug-view
    tests)."""
    from vlm_vpr_ros.localization.pipeline import LocalizationPipeline

    return LocalizationPipeline.open(demo_map)


@pytest.fixture(scope="module")
def image(demo_data):
    """The runtime tests' query frame: a demo image (Sanluri, Sardinia), RGB."""
    from vlm_vpr_ros.files.images import load_image

    return load_image(demo_data / "images" / "546314506564628.jpg")


@pytest.fixture(scope="session")
def demo_country_map(tmp_path_factory, demo_data) -> Path:
    """The same images with one submap per country."""
    from vlm_vpr_ros.mapping.build_images import build_map

    out = tmp_path_factory.mktemp("demo_country_map") / "map"
    build_map(demo_data / "images", demo_data / "coords.csv", out,
              descriptor="vlad_rootsift_fast", partition="country", progress=False)
    return out


@pytest.fixture(scope="session")
def demo_half_map(tmp_path_factory, demo_data) -> tuple[list, Path]:
    """(all coords rows, map of the first 36 demo images): vlad_rootsift_fast at 320 px,
    K=6. Tests that edit it copy it first (map add/remove, map_reload)."""
    from vlm_vpr_ros.mapping.build_images import build_map
    from vlm_vpr_ros.mapping.coords_csv import read_coords_csv

    rows = read_coords_csv(demo_data / "coords.csv")
    work = tmp_path_factory.mktemp("demo_half")
    csv = work / "h1.csv"
    csv.write_text("file,lat,lon\n" + "".join(f"{f},{a!r},{b!r}\n" for f, a, b in rows[:36]))
    build_map(demo_data / "images", csv, work / "map", descriptor="vlad_rootsift_fast",
              descriptor_config={"max_side": 320}, partition="kmeans", clusters=6,
              progress=False)
    return rows, work / "map"


@pytest.fixture(scope="session")
def demo_run(tmp_path_factory) -> tuple[Path, str]:
    """One run of the shipped demo (``vlm-vpr demo``) shared by the tests that need it:
    (its ``demo_out`` folder, what it printed)."""
    import contextlib
    import fcntl
    import io

    from vlm_vpr_ros.evaluation.demo import run_demo

    # one run for the whole session: pytest-xdist workers share their session's base folder
    # (the parent of each worker's own); the first worker runs the demo, the others wait for it
    base = tmp_path_factory.getbasetemp()
    shared = base.parent if os.environ.get("PYTEST_XDIST_WORKER") else base
    folder = shared / "demo_run_shared"
    folder.mkdir(exist_ok=True)
    out, text = folder / "demo_out", folder / "printed.txt"
    with open(shared / "demo_run_shared.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)  # released when the file closes
        if not text.is_file():
            printed = io.StringIO()
            with contextlib.redirect_stdout(printed):
                assert run_demo(out) == 0
            text.write_text(printed.getvalue(), encoding="utf-8")
    return out, text.read_text(encoding="utf-8")
