"""Session-scoped synthetic scenes (exact Snell physics) and their calibrations."""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

from ari_sfm.calibrate import calibrate
from ari_sfm.simulate import make_scene


@pytest.fixture(scope="session")
def single_scene():
    return make_scene("paper_single", seed=0)


@pytest.fixture(scope="session")
def single_ari(single_scene):
    return calibrate(single_scene.dataset, model="ari")


@pytest.fixture(scope="session")
def single_exact(single_scene):
    return calibrate(single_scene.dataset, model="exact")
