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
            "std_msgs"} <= deps
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
    assert list((inst / "lib").glob("python3*/site-packages/vlm_vpr_ros/data/osv5m_demo/"
                                    "images/*.jpg"))
