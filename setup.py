"""Package discovery only (all metadata is in pyproject.toml).

Every folder with an ``__init__.py`` under ``ari_sfm/``, ``factors/`` and
``pipelines/`` is a package; the last two install as ``ari_sfm.factors`` and
``ari_sfm.pipelines`` (``[tool.setuptools.package-dir]``), a renaming that
``[tool.setuptools.packages.find]`` cannot express.
"""
from setuptools import find_packages, setup

PREFIXED = ("factors", "pipelines")  # folders installed under ari_sfm.

setup(packages=find_packages(include=["ari_sfm", "ari_sfm.*"])
      + [f"ari_sfm.{p}" for p in find_packages(include=[f"{d}{s}" for d in PREFIXED for s in ("", ".*")])])
