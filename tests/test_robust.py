"""The Huber loss inside the factors (ari_sfm.factors.robust, issue 15).

- 0.5 |s r|^2 is the Huber loss rho(|r|), continuous at the threshold; the IRLS rows' 0.5 w d^2 plus
  the excess is rho, and a view factor's residual (rows and excess row) has 0.5 |.|^2 = sum of rho;
- the gradient of the linearisation equals a central difference of the error, for the numpy
  backend (VectorizedProblem.linearize / error) and for the GTSAM CustomFactors (graph.linearize
  gradientAtZero / graph.error; both errors equal), at paper_single's initial state with corners on both sides of the
  threshold (square-root IRLS weights gave twice the gradient of their error for the outliers);
- refine-colmap's GTSAM factor's error is its numpy cost (huber_cost).
"""
from __future__ import annotations

import gtsam
import numpy as np
import pytest
from test_vectorized import _initial_state

from ari_sfm.factors.rig_graph import MODELS, RigGraph
from ari_sfm.factors.robust import huber_irls, huber_loss, huber_residual_scale, huber_view_residual, huber_weight
from ari_sfm.factors.vectorized import VectorizedProblem
from ari_sfm.factors.view_factor import view_residuals

HUBER_PX = 0.15  # about half of the corners beyond it at the initial state


def test_scaled_residual_is_the_huber_loss():
    k = 0.7
    d = np.array([0.0, 0.1, 0.7, 0.7 + 1e-12, 1.0, 5.0, 1e6])
    s = huber_residual_scale(d, k)
    np.testing.assert_allclose(0.5 * (s * d) ** 2, huber_loss(d, k), rtol=1e-12, atol=0)
    np.testing.assert_allclose(huber_loss(d[4:], k), k * d[4:] - 0.5 * k * k, rtol=1e-12)
    np.testing.assert_allclose(huber_weight(d[4:], k), k / d[4:], rtol=1e-12)
    assert s[3] == pytest.approx(1.0, abs=1e-9) and np.all(s[:3] == 1.0)  # no kink at k
    sqrt_w, excess = huber_irls(d, k)
    np.testing.assert_allclose(sqrt_w ** 2, huber_weight(d, k), rtol=1e-12)
    np.testing.assert_allclose(0.5 * sqrt_w ** 2 * d ** 2 + excess, huber_loss(d, k), rtol=1e-12)
    # a view's factor residual: 0.5 |.|^2 is the sum of rho (one corner behind the window adds none)
    r = np.random.default_rng(0).normal(0, 1.0, (40, 2))
    res, scale = huber_view_residual(r, k)
    assert res.shape == (81,) and np.array_equal(scale, sqrt_w_of(r, k))
    assert 0.5 * res @ res == pytest.approx(huber_loss(np.linalg.norm(r, axis=1), k).sum(), rel=1e-12)
    r[3] = np.inf
    res, _ = huber_view_residual(r, k)
    assert np.isfinite(res[-1]) and not np.all(np.isfinite(res[6:8]))


def sqrt_w_of(r: np.ndarray, k: float) -> np.ndarray:
    return np.sqrt(huber_weight(np.linalg.norm(r, axis=1), k))


@pytest.fixture(scope="module")
def graph(single_scene):
    """paper_single's ari graph with Huber 0.15 px at its initial state."""
    ds = single_scene.dataset
    rg = RigGraph.build(ds.observations, ds.target, ds.interface, ds.camera_names, _initial_state(ds),
                        model="ari", huber_px=HUBER_PX)
    return rg


def _counts(rg: RigGraph) -> tuple[int, int]:
    """(corners inside, beyond the threshold) at the graph's values."""
    d = np.concatenate([np.linalg.norm(view_residuals(MODELS["ari"], data, keys, rg.values, False)[0].reshape(-1, 2),
                                       axis=1) for data, keys in rg.factor_data])
    return int(np.sum(d <= HUBER_PX)), int(np.sum(d > HUBER_PX))


def _central(f, h: float = 3e-5) -> float:
    """Central difference; small h: the loss is only C1 at the threshold (O(h) from corners crossing it)."""
    return (f(h) - f(-h)) / (2 * h)


def test_numpy_gradient_is_the_errors_gradient(graph):
    inside, beyond = _counts(graph)
    assert inside > 50 and beyond > 50
    problem = VectorizedProblem.from_rig_graph(graph, huber_px=HUBER_PX)
    x = problem.x
    sys = problem.linearize(x)
    assert sys.error == pytest.approx(problem.error(x), rel=1e-12)  # the IRLS system carries the true error
    assert problem.error(x) == pytest.approx(graph.graph.error(graph.values), rel=1e-12)  # GTSAM's factors' error
    rng = np.random.default_rng(7)
    scale = np.ones(len(sys.g_global))
    scale[:problem.n_params] = 0.1  # px of the intrinsics; the rest rad / mm
    for _ in range(3):
        dg = rng.normal(0, 1e-3, len(sys.g_global)) * scale
        df = rng.normal(0, 1e-3, sys.g_frame.shape)
        numeric = _central(lambda t, dg=dg, df=df: problem.error(problem.retract(x, (t * dg, t * df))))
        analytic = float(sys.g_global @ dg + np.sum(sys.g_frame * df))
        assert analytic == pytest.approx(numeric, rel=1e-6)


def test_gtsam_gradient_is_the_errors_gradient(graph):
    values, fg = graph.values, graph.graph
    gradient = fg.linearize(values).gradientAtZero()
    rng = np.random.default_rng(8)
    for _ in range(3):
        delta = gtsam.VectorValues()
        for key in values.keys():
            dim = gradient.at(key).size
            sigma = 0.1 if chr(gtsam.Symbol(key).chr()) == "k" else 1e-3
            delta.insert(key, rng.normal(0, sigma, dim))

        def error(t: float, delta: gtsam.VectorValues = delta) -> float:
            step = gtsam.VectorValues()
            for key in values.keys():
                step.insert(key, t * delta.at(key))
            return fg.error(values.retract(step))

        assert gradient.dot(delta) == pytest.approx(_central(error), rel=1e-6)


def test_refine_colmap_gtsam_factor_error_is_the_huber_cost():
    """refine-colmap's GTSAM graph (one CustomFactor per image) has the numpy solver's error, the sum of
    rho over the observations, and its linearisation's gradient is that error's, at a perturbed start
    with observations on both sides of the threshold."""
    from test_colmap_refine import truth_state

    from ari_sfm.colmap import adapter
    from ari_sfm.colmap.refine.gtsam_graph import GtsamRefinement
    from ari_sfm.colmap.refine.problem import RefractiveProblem
    from ari_sfm.colmap.refine.solver import Solver
    from ari_sfm.simulate.port_survey import port_survey

    truth = port_survey(num_images=4, num_points=60, focal_px=1300, area_mm=(1200, 800), sigma_px=0.2)
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, "camera", estimate_distance=True)
    rng = np.random.default_rng(1)
    start = problem.retract(truth_state(truth, model), rng.normal(0.0, 1e-4, problem.layout.size),
                            rng.normal(0.0, 0.3, (len(model.point3D_ids), 3)))
    huber = 0.5
    d = np.linalg.norm(problem.residuals(start), axis=1)
    assert np.sum(d <= huber) > 30 and np.sum(d > huber) > 30
    refinement = GtsamRefinement(problem, huber)
    graph, values = refinement.graph(start), refinement.values(start)
    assert graph.error(values) == pytest.approx(Solver(problem, huber).cost(start), rel=1e-10)
    gradient = graph.linearize(values).gradientAtZero()
    delta = gtsam.VectorValues()
    for key in values.keys():
        delta.insert(key, rng.normal(0, 1e-3, gradient.at(key).size))

    def error(t: float) -> float:
        step = gtsam.VectorValues()
        for key in values.keys():
            step.insert(key, t * delta.at(key))
        return graph.error(values.retract(step))

    assert gradient.dot(delta) == pytest.approx(_central(error), rel=1e-6)


def test_weighted_residuals_are_the_irls_rows_and_mark_corners_behind_the_window():
    from ari_sfm.factors.robust import weighted_residuals

    rng = np.random.default_rng(3)
    measured = rng.uniform(0, 1000, (50, 2))
    uv = measured + rng.normal(0, 1.5, (50, 2))
    uv[7] = np.nan  # a corner behind the window
    inv_sigma = rng.uniform(0.5, 2.0, 50)
    k = 1.0
    for whitened in (False, True):
        scale, res, dist, excess, beyond = weighted_residuals(uv, measured, k, inv_sigma, whitened, 1e6)
        r = uv - measured
        d = np.linalg.norm(r, axis=1)
        sqrt_w, extra = huber_irls(d, k)
        want_scale = sqrt_w * (inv_sigma if whitened else 1.0)
        ok = np.isfinite(d)
        np.testing.assert_allclose(scale[ok], want_scale[ok], rtol=1e-15)
        np.testing.assert_allclose(res[ok], r[ok] * want_scale[ok, None], rtol=1e-15)
        np.testing.assert_array_equal(res[7], 1e6 * (inv_sigma[7] if whitened else 1.0))
        np.testing.assert_allclose(excess[ok], 0.5 * k * np.maximum(d[ok] - k, 0.0), rtol=1e-15)
        assert beyond and np.isnan(dist[7])
    scale, res, _, excess, beyond = weighted_residuals(uv, measured, -1.0, inv_sigma, False, 1e6)  # no Huber
    assert not beyond and np.all(scale == 1.0) and np.all(excess == 0.0)
