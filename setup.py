"""ament_python build of damon_ros: ``colcon build`` puts the executables in lib/damon_ros."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "damon_ros"

# Executables that ``ros2 run damon_ros <name>`` resolves; each is also on PATH after pip install.
CONSOLE_SCRIPTS = [
    "damon-ros = damon_ros.cli:main",
    "planner = damon_ros.nodes.planner:main",
    "controller = damon_ros.nodes.controller:main",
    "mock_panda = damon_ros.nodes.mock_panda:main",
    "mock_camera = damon_ros.nodes.mock_camera:main",
    "tracker = damon_ros.nodes.tracker:main",
]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.xml")
         + glob("config/*.json")),
        (f"share/{PACKAGE}/models/default", glob("models/default/*")),
    ],
    package_data={PACKAGE: ["py.typed"]},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="damon_ros maintainers",
    maintainer_email="maintainers@damon-ros.dev",
    description="DAMON latent-manifold planner for the Franka Panda as ROS 2 nodes",
    license="Apache-2.0",
    entry_points={"console_scripts": CONSOLE_SCRIPTS},
)
