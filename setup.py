"""Where the packages go: every top-level source folder installs under one namespace,
``hil`` (``timing/`` is ``hil.timing``, ``harness/run/`` is ``hil.harness.run``), so
that nothing of ours takes a global top-level name. ``hil`` itself is a namespace
package: ``hil.adapters``, ``hil.timing`` and ``hil.common`` are the target SDK's
(``sdk/pyproject.toml``, the distribution ``hil-target-sdk``), which this one depends
on. Metadata, dependencies and package data are in pyproject.toml.
"""

from setuptools import find_packages, setup

FOLDERS = ("harness", "scenarios", "targets", "training")

# Folders of data only, shipped as packages (their files: package-data in pyproject.toml).
DATA = ("targets.weights",)

setup(
    packages=[f"hil.{p}" for p in (*find_packages(include=[*FOLDERS, *(f"{f}.*" for f in FOLDERS)]), *DATA)],
    package_dir={f"hil.{f}": f for f in FOLDERS},
)
