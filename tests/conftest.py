"""Session-scoped synthetic scenes (exact Snell physics) and their calibrations."""
from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import pytest

from ari_sfm.calibration.calibrate import calibrate
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


@pytest.fixture(scope="session")
def binocular_calibrations():
    """The bundled binocular dataset (air behind the window) calibrated with every model, default options but no
    lens distortion (the previous writer's default, tests/data/calibration_e6e8196) (~3 s)."""
    from pathlib import Path

    from ari_sfm.io import load_dataset
    from ari_sfm.models.registry import CALIBRATABLE

    dataset = load_dataset(Path(__file__).resolve().parents[1] / "datasets" / "binocular")
    return {m: calibrate(dataset, model=m, distortion=False) for m in CALIBRATABLE}
