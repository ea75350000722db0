"""refine-colmap: the exact refractive refinement of a COLMAP reconstruction made behind a window.

Truth from ari_sfm.simulate.port_survey (exact Snell physics); COLMAP's side is pycolmap's own
bundle adjustment (PINHOLE cameras) of a model built from the simulated correspondences.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm import colmap_export as adapter
from ari_sfm.calibration import load_calibration
from ari_sfm.cli import main
from ari_sfm.colmap_refine import refine_colmap, write_refined
from ari_sfm.colmap_refine.problem import RefractiveProblem, State
from ari_sfm.colmap_refine.refine import Solver
from ari_sfm.colmap_refine.truth import colmap_truth_errors, truth_errors, window_errors
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose
from ari_sfm.simulate.port_survey import port_survey, tank_rig

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")


def colmap_start(truth, focal_scale: float):
    """The model COLMAP would hold: PINHOLE cameras (focal times ``focal_scale``) at the simulated
    correspondences, then pycolmap's own bundle adjustment (its pinhole optimum)."""
    params = [np.r_[p[:2] * focal_scale, p[2:4]] for p in truth.params]
    rec = adapter.reconstruction_from_arrays(params, truth.image_size, truth.sensor_from_rig, truth.rig_from_world,
                                             truth.image_camera, truth.image_frame, truth.xyz, truth.obs_image,
                                             truth.obs_point, truth.obs_uv)
    return rec, adapter.bundle_adjust(rec)


def truth_state(truth, model) -> State:
    """The simulated truth as a refinement state (COLMAP PINHOLE parameters: pixel origin + 0.5)."""
    params = tuple(np.r_[p[:2], p[2:4] + adapter.COLMAP_PIXEL_OFFSET] for p in truth.params)
    sensors = tuple(truth.sensor_from_rig[c] for c in truth.image_camera)
    if truth.mount == "camera":
        normals, dists = np.array(truth.normal_cam), np.array(truth.distance_mm)
    else:
        normals, dists = truth.normal_world[None, :], np.array([truth.plane_mm])
    return State(params, truth.rig_from_world, sensors, normals, dists, truth.xyz[model.point3D_ids - 1].copy())


def poses_of(state: State, model) -> dict[int, Pose]:
    R, t = state.cam_from_world(model)
    return {int(i): Pose(R[k], t[k]) for k, i in enumerate(model.image_ids)}


def noise_limited(truth, rec, mount: str) -> dict:
    """Errors of the same refinement started at the truth: what the noise alone leaves."""
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, mount, estimate_distance=True)
    res = Solver(problem, 2.0).run(truth_state(truth, model), 50)
    e = np.linalg.norm(problem.residuals(res.state), axis=1)
    out = truth_errors(truth, model, res.state.xyz, poses_of(res.state, model))
    out.update(window_errors(truth, res.state.normals, res.state.distances, res.state.rig_from_world[0]))
    out["rms_px"] = float(np.sqrt(np.mean(e ** 2)))
    return out


# ----------------------------------------------------------------------------- Jacobians

@pytest.mark.parametrize("mount", ["camera", "world"])
def test_jacobians_match_central_differences(mount):
    truth = (port_survey(num_images=5, num_points=150, focal_px=1300, area_mm=(1500, 1000)) if mount == "camera"
             else tank_rig(num_frames=3, num_points=120))
    rec = adapter.reconstruction_from_arrays(list(truth.params), truth.image_size, truth.sensor_from_rig,
                                             truth.rig_from_world, truth.image_camera, truth.image_frame, truth.xyz,
                                             truth.obs_image, truth.obs_point, truth.obs_uv)
    model = adapter.model_from_reconstruction(rec)
    problem = RefractiveProblem(model, truth.interface, mount, estimate_distance=True)
    state = truth_state(truth, model)
    lin = problem.linearize(state)
    assert np.allclose(lin.residuals, problem.residuals(state))
    rng = np.random.default_rng(3)
    scale = np.ones(problem.layout.size)
    for ix in problem.layout.intrinsics:
        scale[ix] = 1e3  # pixels-sized intrinsics take bigger steps
    for _ in range(3):
        dg = rng.normal(0.0, 1e-6, problem.layout.size) * scale
        dp = rng.normal(0.0, 1e-5, state.xyz.shape)
        numeric = (problem.residuals(problem.retract(state, dg, dp))
                   - problem.residuals(problem.retract(state, -dg, -dp))) / 2.0
        analytic = (np.einsum("nij,nj->ni", lin.J_g, np.append(dg, 0.0)[lin.index])
                    + np.einsum("nij,nj->ni", lin.J_p, dp[model.obs_point]))
        assert np.max(np.abs(numeric - analytic)) < 1e-6 * np.max(np.abs(analytic))
