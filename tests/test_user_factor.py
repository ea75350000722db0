"""The factor graph is the researcher's API: add your own factor and re-optimise; it weighs what it says.

The view factors carry the pixel sigma (estimated by RigGraph.from_dataset), so
a prior in radians combines with the images as two Gaussians: in the normal's
Unit3 tangent at the free optimum, with Sigma_f its marginal covariance and
delta the prior's offset, the optimum moves to (Sigma_f^-1 + I/s^2)^-1 delta/s^2
and its covariance becomes (Sigma_f^-1 + I/s^2)^-1.
"""
from __future__ import annotations

import gtsam
import numpy as np
import pytest

from ari_sfm.factors import keys
from ari_sfm.factors.backend import solve_graph
from ari_sfm.factors.rig_graph import RigGraph
from ari_sfm.factors.uncertainty import marginal_covariances
from ari_sfm.geometry import angle_between_deg


def _with_prior(dataset, model: str, sigma_px: float, prior: gtsam.Unit3, sigma_rad: float):
    rg = RigGraph.from_dataset(dataset, model=model, sigma_px=sigma_px)
    rg.graph.push_back(gtsam.PriorFactorUnit3(keys.N, prior, gtsam.noiseModel.Isotropic.Sigma(2, sigma_rad)))
    solved = solve_graph(rg, "numpy", huber_px=rg.huber_px).problem
    return rg, solved


@pytest.mark.parametrize("model", ["ari", "exact"])
def test_a_prior_on_the_normal_weighs_what_it_says(single_scene, model):
    """A 0.05 deg prior 0.1 deg away moves the normal by the Gaussian-fusion amount (5 %), and the
    marginal covariance shrinks as predicted (1 %); with the old unit pixel sigma it overrode the images."""
    estimated = RigGraph.from_dataset(single_scene.dataset, model=model)
    if model == "exact":  # the simulated corners have 0.05 px noise; the exact model leaves only that
        assert estimated.sigma_px == pytest.approx(0.05, rel=0.1)
    free = RigGraph.from_dataset(single_scene.dataset, model=model, sigma_px=estimated.sigma_px)
    solved = solve_graph(free, "numpy", huber_px=free.huber_px).problem
    n_free = free.values.atUnit3(keys.N)
    cov_free = marginal_covariances(free, solved)[keys.N]
    s = np.radians(0.05)
    prior = n_free.retract(np.radians([0.1, 0.03]))
    delta = n_free.localCoordinates(prior)
    info = np.linalg.inv(cov_free) + np.eye(2) / s**2
    predicted = np.linalg.solve(info, delta / s**2)

    rg, solved = _with_prior(single_scene.dataset, model, estimated.sigma_px, prior, s)
    moved = n_free.localCoordinates(rg.values.atUnit3(keys.N))
    assert np.linalg.norm(moved - predicted) < 0.05 * np.linalg.norm(predicted)
    assert np.trace(marginal_covariances(rg, solved)[keys.N]) == pytest.approx(np.trace(np.linalg.inv(info)), rel=0.01)

    unit, _ = _with_prior(single_scene.dataset, model, 1.0, prior, s)  # the images weighted as 1 px corners
    assert np.linalg.norm(n_free.localCoordinates(unit.values.atUnit3(keys.N))) > 5.0 * np.linalg.norm(predicted)


def test_a_tight_prior_on_the_normal_from_a_level(single_scene):
    """A prior far tighter than the images (1e-4 deg) holds the normal where the level says."""
    truth_n = np.asarray(single_scene.truth["interface"]["normal_world"])
    rg, _ = _with_prior(single_scene.dataset, "ari", None, gtsam.Unit3(truth_n), np.radians(1e-4))
    assert angle_between_deg(rg.values.atUnit3(keys.N).point3(), truth_n) < 1e-3
