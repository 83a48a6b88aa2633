"""mapf_world: ROS-free grid world core plus the ground-station node.

The planners' search core is C++ (csrc/), compiled here as a plain shared library
(`mapf_world/_native*.so`, C ABI, loaded with ctypes), so colcon builds it with the package.
"""
from glob import glob
from pathlib import Path

from setuptools import Extension, find_packages, setup

PACKAGE = "mapf_world"
# colcon runs this file through a symlink in build/, where csrc/ is not linked: find the sources
# next to the real file. depends= makes a header change rebuild the library.
CSRC = Path(__file__).resolve().parent / "csrc"

native_sources = sorted(glob(str(CSRC / "*.cpp")))
ext_modules = []
if native_sources:
    ext_modules.append(
        Extension(
            f"{PACKAGE}._native",
            sources=native_sources,
            depends=sorted(glob(str(CSRC / "*.hpp"))),
            include_dirs=[str(CSRC)],
            language="c++",
            extra_compile_args=["-O3", "-std=c++17", "-fvisibility=hidden", "-DNDEBUG"],
        )
    )

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    ext_modules=ext_modules,
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
    ],
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="mapf team",
    maintainer_email="mapf@example.org",
    description="Grid world core, planners and the ground-station world node",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "world_node = mapf_world.world_node:main",
            "recorder = mapf_world.recorder_node:main",
        ],
    },
)
