"""pip install . -> the ROS-free core only (soft_twin_core + soft-twin-sim),
with the example robot and scenario files of config/ as package data.

The ROS 2 package soft_twin (interfaces, node) is built by CMake from
CMakeLists.txt/package.xml: `make setup` here, or colcon in a ROS 2 workspace
(see README.md). This file lets the core be used without any ROS install.
"""
import importlib.util
import re
import sys
from pathlib import Path

from setuptools import find_packages, setup

HERE = Path(__file__).resolve().parent
VERSION = re.search(
    r'^__version__\s*=\s*["\']([^"\']+)["\']',
    (HERE / "soft_twin_core" / "__init__.py").read_text(encoding="utf-8"),
    re.M,
).group(1)


def kernel_caches():
    """The numba kernel caches of a warmed-up checkout (`make setup`), as
    package data, when they were compiled from these very sources (the
    warm-up's stamp holds the kernels' source digest): the wheel then loads
    its kernels instead of compiling them for a minute on first use
    (soft_twin_core.engine.kernels._caches). Without them, or stale: none."""
    stamp = HERE / "soft_twin_core" / "__pycache__" / "soft_twin_kernels.sha256"
    if not stamp.is_file():
        return {}
    # the module by its path: its top level needs the standard library only (no numpy here)
    spec = importlib.util.spec_from_file_location(
        "_soft_twin_caches", HERE / "soft_twin_core" / "engine" / "kernels" / "_caches.py")
    caches = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(caches)
    if stamp.read_text().strip() != caches.kernel_digest(HERE / "soft_twin_core"):
        print("soft_twin_core: the kernel caches are stale (run `make setup`); the wheel ships none",
              file=sys.stderr)
        return {}
    dirs = sorted({p.parent.parent for p in (HERE / "soft_twin_core").rglob("__pycache__/*.nbi")})
    out = {".".join(d.relative_to(HERE).parts): ["__pycache__/*.nbi", "__pycache__/*.nbc"] for d in dirs}
    out.setdefault("soft_twin_core", []).append("__pycache__/soft_twin_kernels.sha256")
    return out


setup(
    name="soft_twin_core",
    version=VERSION,
    description="ROS-free Cosserat-rod (PCS) model of soft continuum robots",
    long_description=(HERE / "README.md").read_text(encoding="utf-8") if (HERE / "README.md").exists() else "",
    long_description_content_type="text/markdown",
    license="Apache-2.0",
    python_requires=">=3.10",
    packages=find_packages(include=["soft_twin_core", "soft_twin_core.*"]) + ["soft_twin_core.config"],
    # The example robot and scenario files ship as package data: the
    # checkout's config/ becomes soft_twin_core/config/ in the install, where
    # soft_twin_core.robot.model.config_dirs() finds them (load_model("tendon_arm")).
    package_dir={"soft_twin_core.config": "config"},
    package_data={"soft_twin_core.config": ["robots/*.yaml", "scenarios/*.yaml", "paths/*.yaml"],
                  **kernel_caches()},
    exclude_package_data={"soft_twin_core.config": ["*.py", "params.yaml"]},
    install_requires=[
        "numpy>=1.24,<2.6",
        "scipy>=1.10",
        "PyYAML>=6.0",
        "numba>=0.59",
        "threadpoolctl>=3.1",
    ],
    # optional extras (the versions pinned in requirements/dev.txt are the tested ones):
    # design studies (soft-twin-sim study / workspace); figures, GIF/MP4; MCAP recordings
    extras_require={
        "study": ["dask>=2024.1", "distributed>=2024.1", "pyarrow>=14", "matplotlib>=3.7"],
        "visual": ["matplotlib>=3.7", "imageio>=2.31", "imageio-ffmpeg>=0.4.9"],
        "mcap": ["mcap>=1.1", "mcap-ros2-support>=0.5"],
    },
    entry_points={
        "console_scripts": [
            "soft-twin-sim = soft_twin_core.cli:main",
        ],
    },
)
