"""The simulator: exact physics, the stacking geometry the calibration rests on, files, scenarios.

Every check recomputes the physics independently of the code under test
where it can (vector Snell ray tracing written here, total-least-squares
lines), so a wrong simulator cannot pass by agreeing with itself.
"""
from __future__ import annotations

import json
from collections import Counter, defaultdict

import numpy as np
import pytest

from ari_sfm.geometry import Pose, angle_between_deg
from ari_sfm.models.exact import ExactModel
from ari_sfm.models.pinhole import PinholeModel
from ari_sfm.simulate import SCENARIOS, ScenarioOverrides, make_scene, simulate

SMALL = {"binocular": ScenarioOverrides(num_frames=4), "binocular_underwater": ScenarioOverrides(num_frames=4),
         "arc4": ScenarioOverrides(num_frames=5), "scale16": ScenarioOverrides(num_frames=12)}


@pytest.fixture(scope="session")
def scenes() -> dict:
    """Noise-free scenes (sigma 0), small where the scenario allows."""
    cache: dict = {}

    def get(name: str, sigma_px: float = 0.0, image_scale: float = 1.0):
        key = (name, sigma_px, image_scale)
        if key not in cache:
            cache[key] = make_scene(name, seed=0, sigma_px=sigma_px, overrides=SMALL.get(name), image_scale=image_scale)
        return cache[key]

    return get


def _truth_models(truth: dict, added_mm: float = 0.0) -> dict[str, tuple[ExactModel, Pose]]:
    """ExactModel and cam_from_world of every camera, from truth.json alone."""
    itf = truth["interface"]
    out = {}
    for name, cam in truth["cameras"].items():
        model = ExactModel(PinholeModel(np.array(cam["K"]), np.array(cam["dist"])), np.array(cam["normal_cam"]),
                           itf["thickness_mm"] + added_mm, itf["index"], itf["medium_index"], cam["distance_mm"])
        out[name] = (model, Pose.from_json(cam["cam_from_world"]))
    return out


def _board_world(scene, frame: str) -> tuple[np.ndarray, np.ndarray]:
    ids, pts = scene.dataset.target.points_3d()
    return ids, Pose.from_json(scene.truth["frames"][frame]["world_from_target"]).apply(pts)


def _snell_trace(K: np.ndarray, n_c: np.ndarray, h: float, d: float, n: float, n_m: float,
                 uv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Independent ray tracer: pixel -> medium-side ray (origin on the far face, unit direction)."""
    v = np.linalg.solve(K, np.c_[uv, np.ones(len(uv))].T).T
    v /= np.linalg.norm(v, axis=1, keepdims=True)
    p = v * (h / (v @ n_c))[:, None]
    for eta, depth in ((1.0 / n, d), (n / n_m, None)):
        ci = v @ n_c
        ct = np.sqrt(1.0 - eta**2 * (1.0 - ci**2))
        v = eta * v + (ct - eta * ci)[:, None] * n_c
        if depth is not None:
            p = p + v * (depth / (v @ n_c))[:, None]
    return p, v / np.linalg.norm(v, axis=1, keepdims=True)


@pytest.mark.parametrize("name", ["paper_single", "binocular_underwater", "arc4"])
def test_truth_reprojects_to_noise_free_observations(scenes, name):
    scene = scenes(name)
    frames = {**{o.frame: o for o in scene.dataset.observations}}
    assert frames
    worst = 0.0
    for o in scene.dataset.observations:
        model, cam_from_world = _truth_models(scene.truth, o.added_mm or 0.0)[o.camera]
        ids, X = _board_world(scene, o.frame)
        uv = model.project(cam_from_world.apply(X[o.ids]))
        worst = max(worst, float(np.abs(uv - o.pixels).max()))
    assert worst < 1e-9


@pytest.mark.parametrize("name", ["paper_single", "binocular_underwater", "arc4"])
def test_observations_obey_snell_independently(scenes, name):
    """Trace each observed pixel with Snell's law written here: the ray meets its 3D corner."""
    scene = scenes(name)
    itf = scene.truth["interface"]
    worst = 0.0
    for o in scene.dataset.observations:
        cam = scene.truth["cameras"][o.camera]
        origin, direction = _snell_trace(np.array(cam["K"]), np.array(cam["normal_cam"]), cam["distance_mm"],
                                         itf["thickness_mm"] + (o.added_mm or 0.0), itf["index"],
                                         itf["medium_index"], o.pixels)
        _, X = _board_world(scene, o.frame)
        X_cam = Pose.from_json(cam["cam_from_world"]).apply(X[o.ids])
        gap = np.linalg.norm(np.cross(X_cam - origin, direction), axis=1)
        worst = max(worst, float(gap.max()))
    assert worst < 1e-6  # mm


def test_noise_is_gaussian_with_sigma(scenes):
    exact = scenes("paper_single")
    noisy = scenes("paper_single", sigma_px=0.05)
    res = np.concatenate([(a.pixels - b.pixels).ravel()
                          for a, b in zip(noisy.dataset.observations, exact.dataset.observations)])
    assert [o.frame for o in noisy.dataset.observations] == [o.frame for o in exact.dataset.observations]
    assert abs(res.std() - 0.05) < 0.003 and abs(res.mean()) < 0.003
    stacking = [(a.pixels - b.pixels) for a, b in zip(noisy.dataset.observations, exact.dataset.observations)
                if a.set == "stacking"]
    assert np.std(np.concatenate(stacking)) > 0.04  # stacking is noisy too


@pytest.mark.parametrize("name",
                         ["paper_single", "paper_single_perpendicular", "binocular", "binocular_underwater", "arc4"])
def test_stacking_corners_move_on_lines_through_expansion_center(scenes, name):
    """The physics of the stacking method: per corner, the 6 images lie on one line through K n_c / n_c[2]."""
    scene = scenes(name)
    tracks: dict = defaultdict(list)
    for o in scene.dataset.select("stacking"):
        for i, p in zip(o.ids, o.pixels):
            tracks[(o.camera, o.frame, int(i))].append((o.added_mm, p))
    assert tracks
    worst, moved = 0.0, []
    for (cam, _, _), track in tracks.items():
        track.sort(key=lambda t: t[0])
        P = np.array([p for _, p in track])
        assert len(P) == 6
        e = np.array(scene.truth["cameras"][cam]["expansion_center_px"])
        c = P.mean(axis=0)
        direction = np.linalg.svd(P - c)[2][0]  # total least squares line
        normal = np.array([-direction[1], direction[0]])
        worst = max(worst, abs(float((e - c) @ normal)))
        moved.append(np.linalg.norm(P[-1] - P[0]))
        # monotone: the corner moves away from the expansion centre as glass is added
        r = np.linalg.norm(P - e, axis=1)
        assert np.all(np.diff(r) >= -1e-9)
    assert worst < 0.01
    assert np.median(moved) > 1.0  # the stack really moves the corners (pixels)


def test_expansion_center_is_projection_of_the_normal(scenes):
    scene = scenes("binocular")
    for cam in scene.truth["cameras"].values():
        R = np.array(cam["cam_from_world"]["R"])
        n_c = R @ np.array(scene.truth["interface"]["normal_world"])
        assert np.allclose(n_c, cam["normal_cam"], atol=1e-12)
        p = np.array(cam["K"]) @ n_c
        assert np.allclose(p[:2] / p[2], cam["expansion_center_px"], atol=1e-9)
    first = next(iter(scene.truth["cameras"].values()))
    assert np.allclose(first["cam_from_world"]["R"], np.eye(3)) and np.allclose(first["cam_from_world"]["t"], 0)
    assert scene.truth["interface"]["distance_mm"] == first["distance_mm"]


def test_paper_single_geometry(scenes):
    scene = scenes("paper_single")
    cam = scene.truth["cameras"]["cam0"]
    K = np.array(cam["K"])
    assert cam["image_size"] == [2448, 2048]
    assert abs(K[0, 0] / 3478.0 - 1.0) < 0.012 and K[0, 0] == K[1, 1]
    assert abs(K[0, 2] - 1223.5) <= 20 and abs(K[1, 2] - 1023.5) <= 20
    tilt = angle_between_deg(cam["normal_cam"], [0, 0, 1])
    assert 4.0 <= tilt <= 8.0
    assert 30.0 <= cam["distance_mm"] <= 60.0
    assert scene.truth["interface"]["thickness_mm"] == 50.0 and scene.truth["interface"]["index"] == 1.5168
    calib = scene.dataset.select("calibration")
    assert len(calib) == 12 and all(len(o.ids) == 88 for o in calib)
    assert sorted(o.added_mm for o in scene.dataset.select("stacking")) == [0, 10, 20, 30, 40, 50]
    for o in calib:  # 300-500 mm away, tilted 8-35 deg from the line of sight
        pose = Pose.from_json(scene.truth["frames"][o.frame]["world_from_target"])
        t = scene.dataset.target
        centre = pose.apply(np.array([[(t.inner_corners[0] - 1) * t.square_mm / 2,
                                       (t.inner_corners[1] - 1) * t.square_mm / 2, 0.0]]))[0]
        assert 295 < centre[2] < 505
        assert 7.9 < angle_between_deg(pose.R[:, 2], centre) < 35.1
    corners = np.concatenate([o.pixels for o in calib])  # coverage of the field
    # the whole printed board (one square beyond the corners) is inside every image, so the
    # corners cannot reach the last ~10 %
    assert np.ptp(corners[:, 0]) > 0.8 * 2448 and np.ptp(corners[:, 1]) > 0.75 * 2048
    hist, _, _ = np.histogram2d(corners[:, 0], corners[:, 1], bins=(4, 4), range=((0, 2448), (0, 2048)))
    assert (hist > 0).all()


def test_perpendicular_normal_within_005_deg(scenes):
    for seed in range(3):
        truth = make_scene("paper_single_perpendicular", seed=seed, sigma_px=0.0).truth
        assert angle_between_deg(truth["cameras"]["cam0"]["normal_cam"], [0, 0, 1]) <= 0.05


def test_binocular_rig_and_stage(scenes):
    for name, port, medium in (("binocular", 50.0, 1.0), ("binocular_underwater", 10.0, 1.333)):
        scene = scenes(name)
        truth = scene.truth
        assert truth["interface"]["thickness_mm"] == port and truth["interface"]["medium_index"] == medium
        c1 = Pose.from_json(truth["cameras"]["cam1"]["cam_from_world"]).inverse()
        assert 120 <= np.linalg.norm(c1.t) <= 201
        recon = scene.dataset.select("reconstruction")
        assert len({o.frame for o in recon}) == 11 and len(recon) == 22
        assert sorted({o.stage_mm for o in recon}) == [float(s) for s in range(-10, 11, 2)]
        for set_name in ("calibration", "stacking"):  # every frame seen by both cameras
            per = Counter((o.frame, o.added_mm) for o in scene.dataset.select(set_name))
            assert set(per.values()) == {2}
        # the stage moves the board along one line, 2 mm per step
        origins = {o.stage_mm: Pose.from_json(truth["frames"][o.frame]["world_from_target"]).t for o in recon}
        step = origins[2.0] - origins[0.0]
        assert abs(np.linalg.norm(step) - 2.0) < 1e-9
        assert angle_between_deg(step, truth["interface"]["normal_world"]) < 2.0
        pts = truth["reconstruction_points_world"]["r005"]
        _, X = _board_world(scene, "r005")
        assert np.allclose(pts["xyz"], X)


def test_arc4_partial_visibility_and_outside_expansion_center(scenes):
    scene = make_scene("arc4", seed=0, sigma_px=0.0)
    per = Counter(o.frame for o in scene.dataset.select("calibration"))
    sizes = Counter(per.values())
    assert sum(n for k, n in sizes.items() if k in (2, 3)) >= 0.8 * len(per)  # most frames: 2-3 cameras
    cams_of = defaultdict(set)
    for o in scene.dataset.select("calibration"):
        cams_of[o.frame].add(o.camera)
    for cam in scene.truth["cameras"]:  # every camera shares a frame with another
        assert any(cam in s and len(s) > 1 for s in cams_of.values())
    outside = []
    for cam in scene.truth["cameras"].values():
        w, h = cam["image_size"]
        u, v = cam["expansion_center_px"]
        outside.append(not (0 <= u < w and 0 <= v < h))
    assert outside[0] or outside[-1]  # an outer camera
    assert 18.0 < angle_between_deg(scene.truth["interface"]["normal_world"],
                                    np.mean([Pose.from_json(c["cam_from_world"]).R[2]
                                             for c in scene.truth["cameras"].values()], axis=0)) < 22.0
    assert len({o.camera for o in scene.dataset.select("stacking")}) >= 2


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_builds_valid(scenes, name):
    scene = scenes(name, sigma_px=0.05)
    truth = scene.truth
    assert truth["format"] == "ari-sfm-calibration/1" and truth["model"] == "truth"
    assert truth["scenario"] == name and truth["seed"] == 0 and truth["sigma_px"] == 0.05
    ds = scene.dataset
    assert ds.observations and set(truth["cameras"]) == set(ds.cameras)
    keys = {o.frame for o in ds.observations}
    assert keys <= set(truth["frames"]) and set(truth["frames"]) <= keys | set()
    windows = truth.get("interfaces") or {"window": {**truth["interface"], "cameras": list(truth["cameras"])}}
    assert ("interfaces" in truth) == bool(ds.windows)
    max_added = max((o.added_mm or 0.0) for o in ds.observations)
    ids, pts = ds.target.points_3d()
    centre = {n_: Pose.from_json(c["cam_from_world"]).inverse().t for n_, c in truth["cameras"].items()}
    for itf in windows.values():  # each window's distance is from its first camera
        n = np.array(itf["normal_world"])
        plane = itf["distance_mm"] + n @ centre[itf["cameras"][0]]  # its near face: n . X = plane
        for name_ in itf["cameras"]:  # cameras on the near side, looking into the window
            cam = truth["cameras"][name_]
            assert plane - n @ centre[name_] == pytest.approx(cam["distance_mm"])
            assert cam["distance_mm"] > 5.0 and cam["normal_cam"][2] > 0
        for f in truth["frames"].values():  # every target beyond the far face of the thickest stack
            X = Pose.from_json(f["world_from_target"]).apply(pts)
            assert (X @ n - plane - itf["thickness_mm"] - max_added).min() > 5.0
    for o in ds.observations:  # ids follow the contract, pixels inside the image
        w, h = ds.cameras[o.camera].image_size
        assert np.array_equal(o.ids, ids)
        assert (o.pixels >= 9.5).all() and (o.pixels[:, 0] <= w - 10.5).all() and (o.pixels[:, 1] <= h - 10.5).all()
    json.dumps(truth)


def test_deterministic_and_noise_does_not_move_geometry():
    a = make_scene("binocular", seed=3, sigma_px=0.05, overrides=ScenarioOverrides(num_frames=3))
    b = make_scene("binocular", seed=3, sigma_px=0.05, overrides=ScenarioOverrides(num_frames=3))
    c = make_scene("binocular", seed=3, sigma_px=0.0, overrides=ScenarioOverrides(num_frames=3))
    d = make_scene("binocular", seed=4, sigma_px=0.05, overrides=ScenarioOverrides(num_frames=3))
    assert a.truth["frames"] == b.truth["frames"] == c.truth["frames"]
    assert all(np.array_equal(x.pixels, y.pixels) for x, y in zip(a.dataset.observations, b.dataset.observations))
    assert a.truth["cameras"] != d.truth["cameras"]


def test_image_scale_scales_pixels_exactly(scenes):
    full = scenes("paper_single")
    half = scenes("paper_single", image_scale=0.5)
    assert half.truth["cameras"]["cam0"]["image_size"] == [1224, 1024]
    assert half.truth["frames"] == full.truth["frames"]
    for a, b in zip(full.dataset.observations, half.dataset.observations):
        assert np.allclose(0.5 * (a.pixels + 0.5) - 0.5, b.pixels, atol=1e-9)


def test_unknown_scenario_and_option_raise():
    with pytest.raises(ValueError, match="unknown scenario"):
        make_scene("nope")
    with pytest.raises(ValueError, match="no option"):
        make_scene("paper_single", overrides=ScenarioOverrides(num_cameras=3))


def test_written_dataset_loads(tmp_path):
    from ari_sfm.io import load_dataset

    dataset_dir, truth_path = simulate("binocular_underwater", tmp_path / "bu", seed=1, sigma_px=0.05,
                                       overrides=ScenarioOverrides(num_frames=3))
    assert truth_path.parent == dataset_dir.parent and not (dataset_dir / "truth.json").exists()
    ds = load_dataset(dataset_dir)
    truth = json.loads(truth_path.read_text())
    assert ds.observations is not None and len(ds.calibration) == 3 and len(ds.reconstruction) == 11
    assert ds.interface.medium_index == 1.333 and ds.interface.thickness_mm == 10.0
    assert truth["model"] == "truth" and set(truth["cameras"]) == {"cam0", "cam1"}
    assert {o.frame for o in ds.observations} <= set(truth["frames"])
    assert (tmp_path / "bu" / "truth_observations.json").is_file()


def test_written_images_dataset_has_no_observations(tmp_path):
    from ari_sfm.io import load_dataset

    dataset_dir, truth_path = simulate("paper_single_images", tmp_path / "img", seed=0, image_scale=0.25,
                                       overrides=ScenarioOverrides(num_frames=2))
    ds = load_dataset(dataset_dir)
    assert ds.observations is None and not (dataset_dir / "observations.json").exists()
    entries = ds.entries()
    assert len(entries) == 2 + 6 and all(set(e.images) == {"cam0"} for e in entries)
    for e in entries:
        assert e.images["cam0"].is_file()
    import cv2

    img = cv2.imread(str(ds.calibration[0].images["cam0"]), cv2.IMREAD_UNCHANGED)
    assert img.shape == (512, 612) and img.dtype == np.uint8
    assert img.min() < 60 and img.max() > 200  # black and white squares are there


def test_module_command_line(tmp_path, capsys):
    from ari_sfm.io import load_dataset
    from ari_sfm.simulate.__main__ import main

    assert main(["arc4", str(tmp_path / "a"), "--seed", "2", "--sigma", "0.1", "--num-frames", "5", "--no-images"]) == 0
    assert "truth:" in capsys.readouterr().out
    ds = load_dataset(tmp_path / "a" / "dataset")
    truth = json.loads((tmp_path / "a" / "truth.json").read_text())
    assert len(ds.calibration) == 5 and truth["seed"] == 2 and truth["sigma_px"] == 0.1
    with pytest.raises(SystemExit):
        main(["paper_single", str(tmp_path / "b"), "--num-cameras", "3"])


def test_bundled_sample_matches_its_truth():
    """datasets/sample: images only, truth beside it; the rendered corners sit where the truth says."""
    from pathlib import Path

    import cv2

    from ari_sfm.io import load_dataset, load_observations

    root = Path(__file__).resolve().parents[1] / "datasets"
    ds = load_dataset(root / "sample")
    assert ds.observations is None and not (root / "sample" / "observations.json").exists()
    truth = json.loads((root / "sample_truth.json").read_text())
    assert truth["scenario"] == "paper_single_images" and truth["cameras"]["cam0"]["image_size"] == [1224, 1024]
    assert sum(f.stat().st_size for f in (root / "sample").rglob("*") if f.is_file()) < 20e6
    exact = {(o.set, o.frame, o.added_mm): o for o in load_observations(root / "sample_truth_observations.json")}
    entry = ds.calibration[0]
    img = cv2.imread(str(entry.images["cam0"]), cv2.IMREAD_GRAYSCALE)
    ok, corners = cv2.findChessboardCorners(img, (11, 8))
    assert ok
    corners = cv2.cornerSubPix(img, corners, (5, 5), (-1, -1),
                               (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)).reshape(-1, 2)
    ref = exact[("calibration", entry.key, None)].pixels
    if np.linalg.norm(corners[0] - ref[0]) > np.linalg.norm(corners[-1] - ref[0]):
        corners = corners[::-1]
    assert np.sqrt(np.mean(np.sum((corners - ref) ** 2, axis=1))) < 0.15


def test_project_detector_finds_the_true_corners_in_the_sample():
    """Every sample image detects, with the contract's ids, at the exact corners (rendering = truth)."""
    from pathlib import Path

    import cv2

    from ari_sfm.io import load_dataset, load_observations

    detection = pytest.importorskip("ari_sfm.detection")
    root = Path(__file__).resolve().parents[1] / "datasets"
    ds = load_dataset(root / "sample")
    exact = {(o.set, o.frame, o.added_mm): o for o in load_observations(root / "sample_truth_observations.json")}
    errors = []
    for entry in ds.entries():
        found = detection.detect_corners(cv2.imread(str(entry.images["cam0"]), cv2.IMREAD_GRAYSCALE), ds.target)
        assert found is not None, entry
        ids, pixels = found
        ref = exact[(entry.set, entry.key, entry.added_mm)]
        assert np.array_equal(ids, ref.ids)
        errors.append(pixels - ref.pixels)
    e = np.concatenate(errors)
    assert len(errors) == 18 and np.sqrt(np.mean(np.sum(e**2, axis=1))) < 0.05 and np.abs(e.mean(axis=0)).max() < 0.01


def test_scenario_overrides_are_a_record():
    """The registry's fixed options and a caller's overrides are one record; what a scenario's builder does not
    take, or its entry fixes, is refused naming what it accepts."""
    from ari_sfm.simulate.scenarios import REGISTRY, build_geometry, scenario_options

    assert scenario_options("binocular_underwater_oblique") == ("num_frames",)
    assert REGISTRY["binocular_underwater_oblique"].options.given() == ("underwater", "tilt_deg")
    with pytest.raises(ValueError, match=r"^scenario 'binocular_underwater' has no option underwater; options: "
                                         r"num_frames, stack_added_mm, stage_mm"):
        make_scene("binocular_underwater", overrides=ScenarioOverrides(underwater=False))
    rng = np.random.default_rng([0, 1])
    assert len(build_geometry("arc4", rng, ScenarioOverrides(num_frames=3)).calibration) == 3
    with pytest.raises(TypeError):
        ScenarioOverrides(frame_count=3)  # a misspelt option fails at the record
