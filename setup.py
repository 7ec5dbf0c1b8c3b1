"""ament_python package that also installs with plain pip (no ROS needed)."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "topometric_ros"

setup(
    name=PACKAGE,
    version="0.1.0",
    description="Drift alarms for LiDAR SLAM without ground truth: plane-based map-consistency metrics (PNE, CPV).",
    license="Apache-2.0",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    package_data={PACKAGE: ["segmentation/weights/*"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml")),
        (f"share/{PACKAGE}/launch", glob("launch/*.py")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "numba>=0.59",  # the compiled radius-neighbourhood kernel of MME / MPV / MOM
        "open3d-cpu>=0.19",
        "rosbags>=0.11,<0.12",
        "torch>=2.1",
        "tqdm>=4.60",
        "matplotlib>=3.6",
        "pyyaml>=6.0",
        "mcap>=1.1",  # replay reads a truncated MCAP bag up to the break
        "onnx>=1.17,<2",  # segmentation: in-memory export of the checked weights (torch.onnx needs it)
        "onnxruntime>=1.20,<2",  # segmentation: default CPU backend (eager PyTorch is the fallback)
        "ray>=2.40,<3",  # topometric audit / evaluate / alarms: tasks on a local Ray or a cluster (engine.py)
        "networkx>=3.0",  # the MOM baseline's cliques of mutually orthogonal planes (metrics/mom.py)
    ],
    extras_require={
        "test": ["pytest>=7", "pytest-timeout>=2", "hypothesis>=6", "mcap-ros2-support>=0.5",
                 "evo>=1.20", "kiss-icp>=1.0,<2"],  # kiss-icp: the real LiDAR odometry beside the monitor (experiments)
        "research": ["kiss-icp>=1.0,<2"],
    },
    entry_points={
        "console_scripts": [
            "topometric = topometric_ros.cli:main",
            "topometric_monitor = topometric_ros.node:main",
        ],
    },
    zip_safe=False,
)
