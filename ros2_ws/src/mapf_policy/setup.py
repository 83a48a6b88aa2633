"""mapf_policy: the learned policy (network, losses, training) and the per-robot nodes."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "mapf_policy"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="mapf team",
    maintainer_email="mapf@example.org",
    description="Self-attention Q-network policy, its training, policy node and drive executor",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "policy_node = mapf_policy.policy_node:main",
            "drive_executor = mapf_policy.drive_executor:main",
            "robot_container = mapf_policy.robot_container:main",
        ],
    },
)
