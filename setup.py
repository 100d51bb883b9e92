"""humfall_ros: an ament_python package that also installs with plain pip."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "humfall_ros"
NODES = ["sim_bridge", "state_estimator", "locomotion", "recorder", "multicontact_planner", "estop_planner",
         "ftb_monitor", "safe_fall_controller", "multicontact_executor"]

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/config/scenarios", glob("config/scenarios/*.yaml")),
        (f"share/{PACKAGE}/config/multicontact_plans", glob("config/multicontact_plans/*.json")),
        (f"share/{PACKAGE}/config/multicontact_library", glob("config/multicontact_library/*.json*")),
        (f"share/{PACKAGE}/urdf", glob("urdf/*.urdf")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="humfall_ros developers",
    maintainer_email="dev@humfall.invalid",
    description="Humanoid fall handling for ROS 2 Jazzy",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [f"{n} = {PACKAGE}.nodes.{n}:main" for n in NODES]
        + ["humfall = humfall_ros.cli:main"],
    },
)
