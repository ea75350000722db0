"""Data without stacking and 3D calibration bodies (issue 9): simulated truth with exact
Snell physics, sigma 0.05 px.

- one view of a 3D body per camera is a complete calibration (4 cameras, water);
- the exact model recovers the window normal from refraction alone (single, binocular);
- a declared window (interface.plane): held fixed or as a prior with its sigma;
- --fix-intrinsics with a focal_px hint holds fx = fy, the principal point free;
- under water an exact start never behind the window, even when the ari stage is far off;
- each refusal is one line.
"""
from __future__ import annotations

import logging
import re
from dataclasses import replace

import gtsam
import numpy as np
import pytest

from ari_sfm.calibration.calibrate import calibrate
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose, angle_between_deg, rotation_from_rotvec
from ari_sfm.records import CameraSpec, WindowPlane
from ari_sfm.simulate import ScenarioOverrides, make_scene

SIGMA = 0.05
FLOOR = 1.2 * np.sqrt(2) * SIGMA


def _normal_err(cal, truth) -> float:
    return angle_between_deg(cal.normal_world, truth["interface"]["normal_world"])


def _fx_rel(cal, truth) -> float:
    return max(abs(c.K[0, 0] / truth["cameras"][n]["K"][0][0] - 1) for n, c in cal.cameras.items())


def _declared(scene, frame: str = "f000", tilt_deg: float = 0.0, **sigmas) -> WindowPlane:
    """The true window in the coordinates of ``frame`` (its normal turned by ``tilt_deg``)."""
    tr = scene.truth
    T = Pose.from_json(tr["frames"][frame]["world_from_target"])
    n_w = np.array(tr["interface"]["normal_world"])
    point_w = tr["interface"]["distance_mm"] * n_w  # the face's point nearest camera 0
    n_decl = rotation_from_rotvec(np.radians(tilt_deg) * np.cross(n_w, [1.0, 0, 0]) /
                                  np.linalg.norm(np.cross(n_w, [1.0, 0, 0]))) @ n_w
    return WindowPlane(frame, T.R.T @ n_decl, T.inverse().apply(point_w[None])[0], **sigmas)


def _with_plane(scene, plane):
    ds = scene.dataset
    return replace(ds, interface=replace(ds.interface, plane=plane))


def _without_hints(ds):
    return replace(ds, cameras={n: CameraSpec(n, c.image_size) for n, c in ds.cameras.items()})


@pytest.fixture(scope="module")
def body():
    return make_scene("body3d_water", sigma_px=SIGMA)


@pytest.fixture(scope="module")
def single():
    return make_scene("paper_single_nostack", sigma_px=SIGMA)


@pytest.fixture(scope="module")
def oblique():
    return make_scene("binocular_underwater_oblique", sigma_px=SIGMA)


# ------------------------------------------------------------------ 3D bodies in one view


def test_one_view_body_under_water_by_dlt(body):
    """One view per camera of a 3-level body, 4 cameras, 6 mm glass, water; no hint: DLT."""
    ds = _without_hints(body.dataset)
    assert {o.camera: o.frame for o in ds.observations} == {f"cam{i}": "f000" for i in range(4)}
    cal = calibrate(ds, model="exact")
    assert _fx_rel(cal, body.truth) < 5e-4
    assert _normal_err(cal, body.truth) < 0.1
    assert abs(cal.interface.distance_mm - body.truth["interface"]["distance_mm"]) < 0.5
    assert cal.residuals.rmse_px <= FLOOR


def test_one_view_body_focal_held_principal_point_free(body):
    """--fix-intrinsics with a focal_px hint: fx = fy = focal_px exactly, cx cy estimated."""
    ds = body.dataset
    cams = {n: replace(c, focal_px=body.truth["cameras"][n]["K"][0][0]) for n, c in ds.cameras.items()}
    cal = calibrate(replace(ds, cameras=cams), model="exact", fix_intrinsics=True)
    for n, c in cal.cameras.items():
        K = np.array(body.truth["cameras"][n]["K"])
        assert abs(c.K[0, 0] - K[0, 0]) < 1e-3 and abs(c.K[1, 1] - K[0, 0]) < 1e-3
        w, h = ds.cameras[n].image_size
        centre = np.array([(w - 1) / 2, (h - 1) / 2])  # where the focal hint starts it
        assert np.hypot(*(c.K[:2, 2] - K[:2, 2])) < 0.25 * np.hypot(*(centre - K[:2, 2]))  # free, and found
    assert _normal_err(cal, body.truth) < 0.1
    assert cal.residuals.rmse_px <= FLOOR


def test_fix_intrinsics_without_any_hint_is_refused(body):
    with pytest.raises(AriSfmError, match="focal_px") as e:
        calibrate(_without_hints(body.dataset), model="exact", fix_intrinsics=True)
    assert "\n" not in str(e.value)


def test_nearly_planar_body_without_hints_starts_from_a_resection():
    """DLT cannot start a 2 mm deep body; a resection over the focal length (principal point at the image
    centre) can, the tilted view telling the focal length: the calibration recovers it."""
    scene = make_scene("body3d_water", sigma_px=SIGMA, overrides=ScenarioOverrides(depth_mm=2.0))
    cal = calibrate(_without_hints(scene.dataset), model="exact")
    assert cal.quality.ok
    for name, cam in cal.cameras.items():
        assert cam.K[0, 0] == pytest.approx(scene.truth["cameras"][name]["K"][0][0], rel=0.01)


def test_too_shallow_for_dlt_asks_for_a_focal_hint_and_the_hint_is_used():
    """A 30 x 30 mm, 15 mm deep patch at 600 mm with 1 px noise: DLT's K start is not a camera
    (principal point or aspect off): one line asking for a hint; with the hint, no DLT."""
    from ari_sfm.init.zhang import calibrate_views

    scene = make_scene("body3d_shallow", sigma_px=1.0)
    keep = [r * 11 + c for r in range(3) for c in range(3)]
    obs = tuple(replace(o, ids=o.ids[np.isin(o.ids, keep)], pixels=o.pixels[np.isin(o.ids, keep)])
                for o in scene.dataset.observations)
    ds = replace(scene.dataset, observations=obs)
    with pytest.raises(AriSfmError, match="too shallow for DLT.*focal_px") as e:
        calibrate(_without_hints(ds), model="exact")
    assert "\n" not in str(e.value)
    spec = ds.cameras["cam0"]
    z = calibrate_views(ds.target, spec, [obs[0]])
    w, h = spec.image_size
    assert 0 <= z.K[0, 2] <= w - 1 and 0 <= z.K[1, 2] <= h - 1


# ------------------------------------------------------------------ no stacking: exact observes the normal


def test_exact_without_stacking_single(single):
    cal = calibrate(single.dataset, model="exact")
    assert _normal_err(cal, single.truth) < 0.3
    assert _fx_rel(cal, single.truth) < 5e-4
    assert cal.residuals.rmse_px <= FLOOR


def test_exact_without_stacking_binocular():
    scene = make_scene("binocular_nostack", sigma_px=SIGMA)
    cal = calibrate(scene.dataset, model="exact")
    assert _normal_err(cal, scene.truth) < 0.3
    assert _fx_rel(cal, scene.truth) < 5e-4
    assert cal.residuals.rmse_px <= FLOOR


def test_ari_without_stacking_names_both_ways_out(single):
    with pytest.raises(AriSfmError) as e:
        calibrate(single.dataset, model="ari")
    msg = str(e.value)
    assert "\n" not in msg and "--model exact" in msg and "interface.plane" in msg


# ------------------------------------------------------------------ a declared window


@pytest.mark.parametrize("seed", [0, 1])
def test_declared_plane_held_fixed_under_water(seed):
    """The window held where it is declared: exact reaches the floor, the distance is the declared one.
    (Seed 1: the ari stage's poses would place the plane behind the cameras; exact places it.)"""
    scene = make_scene("binocular_underwater_oblique", seed=seed, sigma_px=SIGMA)
    cal = calibrate(_with_plane(scene, _declared(scene)), model="exact", uncertainty=False)
    assert _normal_err(cal, scene.truth) < 0.01
    assert abs(cal.interface.distance_mm - scene.truth["interface"]["distance_mm"]) < 0.05
    assert cal.residuals.rmse_px <= FLOOR


def test_declared_plane_lets_ari_run_without_stacking(single):
    """In air, ari with a declared plane runs (its paraxial bias remains) and reports the distance."""
    cal = calibrate(_with_plane(single, _declared(single)), model="ari")
    assert _normal_err(cal, single.truth) < 0.6
    assert cal.interface.distance_mm is not None
    exact = calibrate(_with_plane(single, _declared(single)), model="exact")
    assert _normal_err(exact, single.truth) < 0.01
    assert abs(exact.interface.distance_mm - single.truth["interface"]["distance_mm"]) < 0.1


def test_declared_plane_fixed_versus_prior(single):
    """A plane declared 1 deg off: held fixed, the normal stays the declared one in its frame's
    coordinates (so ~1 deg off the truth); as a 10-deg prior the images win."""
    plane = _declared(single, tilt_deg=1.0)
    held = calibrate(_with_plane(single, plane), model="exact")
    assert angle_between_deg(held.normal_world, held.frames[plane.frame].R @ plane.normal) < 1e-3
    assert 0.9 < _normal_err(held, single.truth) < 1.1
    prior = calibrate(_with_plane(single, _declared(single, tilt_deg=1.0, sigma_deg=10.0, sigma_mm=50.0)),
                      model="exact")
    assert _normal_err(prior, single.truth) < 0.3


def test_declared_plane_on_an_unknown_frame_is_refused(single):
    with pytest.raises(AriSfmError, match="interface.plane.frame: 'nope'") as e:
        calibrate(_with_plane(single, replace(_declared(single), frame="nope")), model="exact")
    assert "\n" not in str(e.value)


def test_window_plane_factor_jacobians():
    """The plane factor's Jacobians against central differences in GTSAM's tangent spaces."""
    from ari_sfm.factors import keys as K_
    from ari_sfm.factors.window_plane import plane_errors

    rng = np.random.default_rng(3)
    plane = WindowPlane("f", np.array([0.1, -0.2, 0.97]) / np.linalg.norm([0.1, -0.2, 0.97]),
                        np.array([5.0, -3.0, 40.0]))
    values = gtsam.Values()
    values.insert(K_.N, gtsam.Unit3(np.array([0.05, 0.1, 1.0])))
    values.insert(K_.X(0), gtsam.Pose3(gtsam.Rot3.Expmap(rng.normal(size=3) * 0.3), rng.normal(size=3) * 100))
    values.insert(K_.H, np.array([37.0]))
    e0, Hs = plane_errors(plane, values, K_.X(0), True, True)
    eps = 1e-6
    for key, H, dim in zip([K_.N, K_.X(0), K_.H], Hs, [2, 6, 1]):
        num = np.zeros((len(e0), dim))
        for j in range(dim):
            d = np.zeros(dim)
            d[j] = eps
            out = []
            for s in (1, -1):
                v = gtsam.Values(values)
                if key == K_.N:
                    v.update(key, values.atUnit3(key).retract(s * d))
                elif key == K_.H:
                    v.update(key, values.atVector(key) + s * d)
                else:
                    v.update(key, values.atPose3(key).retract(s * d))
                out.append(plane_errors(plane, v, K_.X(0), True, False)[0])
            num[:, j] = (out[0] - out[1]) / (2 * eps)
        np.testing.assert_allclose(H, num, atol=1e-5)


# ------------------------------------------------------------------ under water: never behind the window


def _true_state(scene):
    """The simulated truth as a RigState (calibration frames)."""
    from ari_sfm.factors.rig_graph import RigState

    tr, names = scene.truth, scene.dataset.camera_names
    frames = {o.frame for o in scene.dataset.select("calibration")}
    return RigState({n: np.r_[np.array(tr["cameras"][n]["K"])[[0, 1, 0, 1], [0, 1, 2, 2]], np.zeros(5)] for n in names},
                    {n: Pose.from_json(tr["cameras"][n]["cam_from_world"]) for n in names},
                    np.array(tr["interface"]["normal_world"]),
                    {f: Pose.from_json(tr["frames"][f]["world_from_target"]) for f in frames},
                    tr["interface"]["distance_mm"])


def test_under_water_exact_recovers_when_the_ari_stage_is_far_off(oblique, caplog):
    """A distance hint of 2.4 m (true ~48 mm): the ari stage ends far off, the exact start is searched
    inside the valid interval and the exact stage reaches the noise floor."""
    ds = replace(oblique.dataset, interface=replace(oblique.dataset.interface, distance_mm=2400.0))
    with caplog.at_level(logging.INFO, logger="ari_sfm.calibration.calibrate"):
        cal = calibrate(ds, model="exact")
    ari_distance = float(re.search(r"ari bundle adjustment.*window distance ([\d.]+) mm", caplog.text).group(1))
    truth = oblique.truth["interface"]["distance_mm"]
    assert ari_distance > 10 * truth
    assert cal.residuals.rmse_px <= FLOOR
    assert abs(cal.interface.distance_mm - truth) < 0.2
    assert _normal_err(cal, oblique.truth) < 0.3


def test_oblique_seed_1_ari_start_at_its_own_window_calibrates():
    """Issue 14: the ari stage ends with the window at ~1090 mm and the targets where that window puts
    their apparent depths (15-180 mm from the cameras; truth 380-540 mm): with the targets held, no
    distance separated cameras and corners and calibrate refused. The exact start moves the targets
    with the window (keeping their apparent depths) and recovers the truth."""
    scene = make_scene("binocular_underwater_oblique", seed=1, sigma_px=SIGMA)
    cal = calibrate(scene.dataset, model="exact", uncertainty=False)
    assert cal.residuals.rmse_px <= FLOOR
    assert _normal_err(cal, scene.truth) < 0.3
    assert _fx_rel(cal, scene.truth) < 5e-4
    assert abs(cal.interface.distance_mm - scene.truth["interface"]["distance_mm"]) < 0.2


def test_moving_the_window_moves_the_targets_at_their_apparent_depth(oblique):
    """A state like the ari stage's (window 1090 mm, targets at the apparent depths it implies):
    held targets leave no valid distance or exclude the truth; moved with the window the interval
    holds the truth, and moving the window back is the truth again (a round trip)."""
    from ari_sfm.init.window_start import distance_interval, moved_window, target_shift_mm

    ds, tr = oblique.dataset, oblique.truth
    n_m, t, h = ds.interface.medium_index, ds.interface.thickness_mm, tr["interface"]["distance_mm"]
    assert target_shift_mm(1.0, 1090.0, h) == 0.0  # in air the targets stay
    truth = _true_state(oblique)
    far = moved_window(truth, 1090.0, n_m)
    f = next(iter(far.world_from_target))
    shift = (far.world_from_target[f].t - truth.world_from_target[f].t) @ truth.normal_world
    assert shift == pytest.approx(-(n_m - 1.0) * (1090.0 - h))
    lo, hi = distance_interval(far, ds.observations, ds.target, t)
    assert not lo < h < hi
    lo, hi = distance_interval(far, ds.observations, ds.target, t, n_m)
    assert lo < h < hi
    # the interval's far end: the nearest corner exactly on the far face after the move
    edge = moved_window(far, hi, n_m)
    lo_e, hi_e = distance_interval(edge, ds.observations, ds.target, t)
    assert hi_e == pytest.approx(hi, abs=1e-9)
    back = moved_window(far, h, n_m)
    for fr, pose in truth.world_from_target.items():
        np.testing.assert_allclose(back.world_from_target[fr].t, pose.t, atol=1e-9)


@pytest.mark.parametrize("backend", ["numpy", "gtsam"])
def test_lm_from_either_end_of_the_valid_interval(oblique, backend):
    """Started next to either end of the interval where every corner is beyond the window, LM
    (both backends) converges without abort: a trial step putting a corner behind the window costs
    >= 1e11 and is rejected."""
    from ari_sfm.factors.rig_graph import RigGraph
    from ari_sfm.factors.vectorized import VectorizedProblem, optimize_graph
    from ari_sfm.init.window_start import distance_interval

    ds, tr, names = oblique.dataset, oblique.truth, oblique.dataset.camera_names
    state = _true_state(oblique)
    lo, hi = distance_interval(state, ds.observations, ds.target, ds.interface.thickness_mm)
    assert lo < tr["interface"]["distance_mm"] < hi

    def graph(h):
        return RigGraph.build(ds.observations, ds.target, ds.interface, names, replace(state, distance_mm=h),
                              model="exact", estimate_distance=True, huber_px=1.0)

    beyond = graph(hi + 5.0)
    assert beyond.graph.error(beyond.values) > 1e11
    assert VectorizedProblem.from_rig_graph(beyond, huber_px=1.0).error() > 1e11
    for h in (lo + 0.01 * (hi - lo), hi - 0.001 * (hi - lo)):
        rg = graph(h)
        out = optimize_graph(rg, backend, 100, 1.0)
        r = np.concatenate([x for _, x in rg.residuals()])
        assert np.sqrt((r ** 2).sum(axis=1).mean()) <= FLOOR
        assert abs(out.distance_mm - tr["interface"]["distance_mm"]) < 0.2


def test_a_start_behind_the_window_names_camera_and_frame(oblique):
    """The geometric check agrees with the exact model (no ray where it names a view) and names
    camera and frame in one line; a camera beyond the window is named alone."""
    from ari_sfm.factors.rig_graph import RigGraph
    from ari_sfm.factors.vectorized import INVALID_RESIDUAL
    from ari_sfm.init.exact_start import check_in_front
    from ari_sfm.init.window_start import not_beyond

    ds, names = oblique.dataset, oblique.dataset.camera_names
    args = (ds.observations, ds.target, ds.interface.thickness_mm)
    assert not_beyond(_true_state(oblique), *args) is None
    state = replace(_true_state(oblique), distance_mm=2400.0)
    camera, frame = not_beyond(state, *args)
    rg = RigGraph.build(ds.observations, ds.target, ds.interface, names, state, model="exact", estimate_distance=True)
    r = next(r for o, r in rg.residuals() if (o.camera, o.frame) == (camera, frame))
    assert np.all(np.abs(r) >= INVALID_RESIDUAL)
    with pytest.raises(AriSfmError, match=rf"camera {camera} frame {frame}: a corner is not beyond the window") as e:
        check_in_front(ds, state)
    assert "\n" not in str(e.value)
    assert not_beyond(replace(state, distance_mm=-5.0), *args) == ("cam0", None)


# ------------------------------------------------------------------ the command line


def test_cli_without_stacking(tmp_path):
    """calibrate (ari by default) refuses in one line naming both ways out; run picks exact;
    calibrate --model exact --fix-intrinsics holds the focal_px hint."""
    import json

    from click.testing import CliRunner

    from ari_sfm.cli import main

    runner = CliRunner()
    r = runner.invoke(main, ["simulate", "paper_single_nostack", "-o", str(tmp_path / "sim"), "--no-images"])
    assert r.exit_code == 0, r.output
    ds = str(tmp_path / "sim" / "dataset")
    r = runner.invoke(main, ["calibrate", ds, "-o", str(tmp_path / "a"), "--model", "ari"])
    assert r.exit_code == 1 and not (tmp_path / "a" / "calibration.json").exists()
    lines = [ln for ln in r.output.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: ") and "--model exact" in lines[0], r.output
    r = runner.invoke(main, ["run", ds, "-o", str(tmp_path / "run")])
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "run" / "run.json").read_text())["model"] == "exact"
    r = runner.invoke(main, ["calibrate", ds, "-o", str(tmp_path / "f"), "--model", "exact", "--fix-intrinsics"])
    assert r.exit_code == 0, r.output
    cal = json.loads((tmp_path / "f" / "calibration.json").read_text())
    truth = json.loads((tmp_path / "sim" / "truth.json").read_text())
    import yaml

    focal = yaml.safe_load((tmp_path / "sim" / "dataset" / "rig.yaml").read_text())["cameras"]["cam0"]["focal_px"]
    K = np.array(cal["cameras"]["cam0"]["K"])
    assert abs(K[0, 0] - focal) < 1e-3 and abs(K[1, 1] - focal) < 1e-3
    assert abs(K[0, 2] - np.array(truth["cameras"]["cam0"]["K"])[0, 2]) < 10.0  # free (the hint is 1 % off)


# ------------------------------------------------------------------ the start searches


def test_tilt_candidates_and_searches():
    from ari_sfm.init.window_start import search_distance, search_normal, tilt_candidates

    axis = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    cands = tilt_candidates(axis, (4.0, 8.0), 6)
    assert len(cands) == 13
    angles = sorted(angle_between_deg(c, axis) for c in cands)
    np.testing.assert_allclose(angles, [0.0] + [4.0] * 6 + [8.0] * 6, atol=1e-9)
    hidden = cands[9]
    np.testing.assert_allclose(search_normal(lambda n: angle_between_deg(n, hidden), axis, (4.0, 8.0), 6), hidden)
    # a cost infinite near one end (corners behind the window there), a minimum at 37 mm
    cost = lambda h: np.inf if h > 300 else (h - 37.0) ** 2 + 1.0  # noqa: E731
    assert abs(search_distance(cost, 0.0, 370.0) - 37.0) < 0.05
    assert abs(search_distance(cost, 0.0, 370.0, current=2400.0) - 37.0) < 0.05  # outside: not a candidate


def test_declared_plane_prior_same_in_both_backends(single):
    plane = _declared(single, tilt_deg=0.5, sigma_deg=0.5, sigma_mm=2.0)
    a, b = (calibrate(_with_plane(single, plane), model="exact", backend=x, uncertainty=False)
            for x in ("numpy", "gtsam"))
    assert angle_between_deg(a.normal_world, b.normal_world) < 1e-5
    assert abs(a.interface.distance_mm - b.interface.distance_mm) < 1e-4
    assert _normal_err(a, single.truth) < 0.6  # the declared normal is 0.5 deg off


def test_rig_graph_from_dataset_without_stacking(single):
    from ari_sfm.factors.rig_graph import RigGraph

    with pytest.raises(AriSfmError, match="normal is not observable"):
        RigGraph.from_dataset(single.dataset, model="ari")
    rg = RigGraph.from_dataset(_with_plane(single, _declared(single)), model="ari")
    assert rg.graph.size() == len(rg.factor_data) + 1  # the views and the plane


def test_coarse_to_fine_normal_search_is_the_grids_best():
    """On a one-minimum landscape (the angle to a hidden normal anywhere within 20 deg) the coarse-to-fine
    search returns the whole grid's best candidate, scoring at most 24 of its 33 directions."""
    from ari_sfm.init.window_start import search_normal, tilt_candidates

    axis = np.array([0.1, -0.2, 1.0]) / np.linalg.norm([0.1, -0.2, 1.0])
    grid = tilt_candidates(axis)
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(axis, e1)
    rng = np.random.default_rng(0)
    for _ in range(60):
        t, a = np.radians(rng.uniform(0.0, 20.0)), rng.uniform(0.0, 2 * np.pi)
        hidden = np.cos(t) * axis + np.sin(t) * (np.cos(a) * e1 + np.sin(a) * e2)
        calls = []
        found = search_normal(lambda n, calls=calls, hidden=hidden: calls.append(1) or angle_between_deg(n, hidden),
                              axis)
        best = grid[int(np.argmin([angle_between_deg(n, hidden) for n in grid]))]
        np.testing.assert_allclose(found, best)
        assert len(calls) <= 24


def test_search_corners_cut_large_views_the_same_way_every_time():
    import importlib

    from ari_sfm.records import Observation

    C = importlib.import_module("ari_sfm.init.exact_start")
    big = Observation("cam0", "calibration", "f000", np.arange(1600), np.zeros((1600, 2)))
    small = Observation("cam1", "calibration", "f000", np.arange(50), np.zeros((50, 2)))
    other = Observation("cam1", "calibration", "f001", np.arange(1600), np.zeros((1600, 2)))
    cut = C._search_corners((big, small, other), ["f000"], 160)
    assert [o.camera for o in cut] == ["cam0", "cam1"]  # only the searched frames
    assert len(cut[0].ids) == 160 and len(set(cut[0].ids)) == 160 and cut[1] is small
    np.testing.assert_array_equal(cut[0].ids, C._search_corners((big,), ["f000"], 160)[0].ids)
