"""The package builds with colcon into the real ament layout that ``ros2 run`` relies on.

``ros2 run damon_ros X`` asks ament_index for the package prefix and runs
``<prefix>/lib/damon_ros/X``; this test does exactly that for every console script the
package declares, after a real ``colcon build`` into a temporary workspace.
"""

from __future__ import annotations

import configparser
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SOURCES = ["package.xml", "setup.py", "setup.cfg", "resource", "damon_ros", "config", "models"]
EXPECTED_EXECUTABLES = {"damon-ros", "planner", "controller", "mock_panda", "mock_camera",
                        "tracker"}


def _declared_executables(install: Path) -> set[str]:
    """Console scripts as the installed distribution declares them (entry_points.txt)."""
    site = next(install.glob("lib/python3*/site-packages"))
    entry_points = next(site.glob("damon_ros-*/entry_points.txt"))
    parser = configparser.ConfigParser()
    parser.read(entry_points)
    return set(parser["console_scripts"])


@pytest.fixture(scope="module")
def workspace(tmp_path_factory) -> Path:
    colcon = Path(sys.executable).with_name("colcon")
    if not colcon.exists():
        pytest.fail(f"colcon is not installed next to {sys.executable}")
    ws = tmp_path_factory.mktemp("ws")
    src = ws / "src" / "damon_ros"
    src.mkdir(parents=True)
    for name in SOURCES:
        path = ROOT / name
        if path.is_dir():
            shutil.copytree(path, src / name, ignore=shutil.ignore_patterns("__pycache__"))
        else:
            shutil.copy2(path, src / name)
    env = dict(os.environ, PATH=f"{colcon.parent}{os.pathsep}{os.environ['PATH']}")
    result = subprocess.run(
        [str(colcon), "build", "--base-paths", "src"], cwd=ws, env=env,
        capture_output=True, text=True, timeout=240,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    return ws


def test_package_xml_is_format3_ament_python_with_valid_maintainer():
    root = ET.parse(ROOT / "package.xml").getroot()
    assert root.get("format") == "3"
    assert root.findtext("export/build_type") == "ament_python"
    email = root.find("maintainer").get("email")
    assert "@" in email and "." in email.split("@")[1]
    depends = {d.text for d in root.findall("depend")}
    assert {"rclpy", "std_msgs", "geometry_msgs", "sensor_msgs", "trajectory_msgs", "nav_msgs",
            "visualization_msgs", "diagnostic_msgs", "std_srvs"} <= depends


def test_colcon_built_it_as_an_ament_package(workspace):
    # colcon-ros writes package.dsv hooks only for packages it recognised as ROS packages.
    share = workspace / "install" / "damon_ros" / "share" / "damon_ros"
    assert (share / "package.xml").is_file()
    assert (share / "package.dsv").is_file()
    assert (workspace / "install/damon_ros/share/ament_index/resource_index/packages/damon_ros"
            ).is_file()
    assert list((share / "config").glob("*.yaml")), "config/*.yaml is not installed"


def test_every_executable_resolves_as_ros2_run_does(workspace):
    install = workspace / "install" / "damon_ros"
    site = next(install.glob("lib/python3*/site-packages"))
    env = dict(os.environ, AMENT_PREFIX_PATH=str(install),
               PYTHONPATH=os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")]))
    lookup = (
        "from ament_index_python.packages import get_package_prefix;"
        "print(get_package_prefix('damon_ros'))"
    )
    prefix = subprocess.run(
        [sys.executable, "-c", lookup], env=env, capture_output=True, text=True, timeout=60,
        check=True,
    ).stdout.strip()
    assert Path(prefix) == install
    executables = _declared_executables(install)
    assert executables >= EXPECTED_EXECUTABLES
    for name in sorted(executables):
        exe = Path(prefix) / "lib" / "damon_ros" / name
        assert exe.is_file() and os.access(exe, os.X_OK), f"{exe} is missing or not executable"
        run = subprocess.run([str(exe), "--help"], env=env, cwd=workspace, capture_output=True,
                             text=True, timeout=120)
        assert run.returncode == 0, f"{name} --help failed: {run.stderr[-2000:]}"
        assert "usage" in run.stdout.lower(), f"{name} --help printed no usage"
