"""Package layout of the wheel (the metadata is in pyproject.toml).

The repository keeps ``conf/`` and ``plugins/`` at its root; the wheel installs them as ``b3dgs/conf``
(package data, found by :func:`b3dgs.conf_dir`) and as the package ``b3dgs_plugins`` (a name no other
project's top-level ``plugins`` can clash with). The ``b3dgs_plugins`` symlink at the root makes the same
import name work in a source checkout without an install. New subpackages are picked up by the
discovery below (``tests/test_install.py`` checks that every source file lands in the wheel).
"""
from setuptools import find_namespace_packages, setup

PLUGIN_PACKAGES = find_namespace_packages(include=["plugins", "plugins.*"], exclude=["*.__pycache__"])

setup(
    packages=find_namespace_packages(include=["b3dgs", "b3dgs.*", "hydra_plugins", "hydra_plugins.*"],
                                     exclude=["*.__pycache__"])
    + ["b3dgs.conf"] + ["b3dgs_plugins" + p[len("plugins"):] for p in PLUGIN_PACKAGES],
    package_dir={"b3dgs.conf": "conf", "b3dgs_plugins": "plugins"},
    package_data={"b3dgs.conf": ["**/*.yaml"], "b3dgs.render.csrc": ["*.cpp", "*.h"]},
)
