"""ament_python build of vlm_vpr_ros (works with colcon and with plain pip)."""

from glob import glob
import os

from setuptools import find_packages, setup

package_name = "vlm_vpr_ros"


def _files(pattern: str) -> list[str]:
    return sorted(p for p in glob(pattern) if os.path.isfile(p))


setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=["vlm_vpr_ros", "vlm_vpr_ros.*",
                                    "msg_adapters", "msg_adapters.*"]),
    package_data={"vlm_vpr_ros": ["data/*.*", "data/*/*.*", "data/*/*/*.*"]},
    include_package_data=True,
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        # ROS convention: launch files (and their params/profile files) in share/<pkg>/launch
        ("share/" + package_name + "/launch", _files("launch_scripts/*")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="vlm_vpr_ros maintainers",
    maintainer_email="maintainers@vlm-vpr-ros.invalid",
    description="VLM-guided visual place recognition (kidnapped-robot geo-localization) for ROS 2",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "vlm-vpr = vlm_vpr_ros.cli:main",
            "vlm_vpr_node = vlm_vpr_ros.ros.node:main",
            "vlm_vpr_lifecycle_node = vlm_vpr_ros.ros.node:lifecycle_main",
        ],
    },
)
