"""ament_python package definition; ``colcon build`` and ``pip install`` both use it."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "dyn_node"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    package_data={PACKAGE: ["urdf/*.urdf", "schemas/*.json", "config/*.yaml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="dyn_node developers",
    maintainer_email="dev@dyn-node.invalid",
    description="Dynamic-feasibility monitor for ROS 2: RNEA torques, limit checks, MCAP audit.",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "dyn_node = dyn_node.ros.node:main",
            "dyn_sim = dyn_node.ros.sim_node:main",
            "dyn-audit = dyn_node.audit.bag_audit:main",
            "dyn-bag-recover = dyn_node.bag.recover:main",
            "dyn-check = dyn_node.audit.check:main",
            "dyn-fleet = dyn_node.fleet.engine:main",
            "dyn_node_demo = dyn_node.ros.demo:main",
        ],
    },
)
