"""Install pcdet_atlas: `pip install -e .[test]`. The official Waymo metric runs in its own venv
(tools/official_waymo_metric/setup_venv.sh), not through the `[waymo]` extra listed below."""

from pathlib import Path

from setuptools import find_packages, setup

ROOT = Path(__file__).resolve().parent
version_ns: dict = {}
exec((ROOT / "pcdet_atlas" / "version.py").read_text(), version_ns)

setup(
    name="pcdet_atlas",
    version=version_ns["__version__"],
    description="ATLAS: black-box LiDAR spoofing benchmark, a pure-PyTorch OpenPCDet plugin",
    long_description=(ROOT / "README.md").read_text(),
    long_description_content_type="text/markdown",
    packages=find_packages(include=["pcdet_atlas", "pcdet_atlas.*"]),
    python_requires=">=3.10",
    install_requires=[
        "torch>=2.1",
        "numpy>=1.23",
        "easydict>=1.10",
        "pyyaml>=6.0",
        "tensorboardX>=2.6",
        "tqdm>=4.60",
        "matplotlib>=3.7",
        "scipy>=1.10",
        "jsonschema>=4.18",
        # Waymo's submission .bin (pcdet_atlas/datasets/waymo_submission.py) uses
        # message_factory.GetMessageClass and google.protobuf.unknown_fields (tested with 7.36)
        "protobuf>=4.22",
    ],
    extras_require={
        "test": ["pytest>=7", "hypothesis>=6.80", "shapely>=2.0", "ruff==0.17.5"],
        # The official metric pins TF 2.13 / numpy 1.23; install it in its own venv
        # (tools/official_waymo_metric/ does this); listed here for completeness.
        "waymo": ["waymo-open-dataset-tf-2-12-0==1.6.7"],
    },
    include_package_data=True,
)
