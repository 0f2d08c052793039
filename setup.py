"""Packages of the maglog distribution, discovered rather than listed: each top-level
folder of DESIGN.md's layout is the package ``maglog.<folder>``, and every folder below it
that holds an ``__init__.py`` is one of its subpackages. The rest of the metadata is in
pyproject.toml."""

from setuptools import find_packages, setup

#: The folders that make up the ``maglog`` namespace (tests/ and bench/ are not shipped).
ROOTS = ("hw", "sw", "sim", "calib", "cli")

setup(
    package_dir={f"maglog.{root}": root for root in ROOTS},
    packages=[f"maglog.{root}.{sub}" if sub else f"maglog.{root}"
              for root in ROOTS for sub in ["", *find_packages(root)]],
)
