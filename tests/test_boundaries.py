"""Architecture guard: the localization core never imports ROS, message packages or mcap."""

import ast
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
