"""Architecture guard: the localization core never imports ROS, message packages or mcap."""

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "vlm_vpr_ros"
#: the edges, allowed to talk to ROS / bags
EDGES = {"node.py", "node_wiring.py", "cli", "bags"}
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
    for node in (PKG / "node.py", PKG / "node_wiring.py"):
        if node.exists():
            n = len(node.read_text().splitlines())
            assert n <= 300, f"{node.name} has {n} lines: move logic into the core/msg_adapters"
