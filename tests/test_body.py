"""3D calibration bodies from their images (ari_sfm.body, DATASET_FORMAT 1.3): dots in a rendered tank image
(test_cavity's body through a 6 mm wall into water, exact Snell projection) among particles, a wall's streak,
glare and a faint reflection, identified from 4 clicked points perturbed by up to 3 px."""
from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.body import BodyHints, BodyWindow, ClickError, DotOptions, find_body, find_dots
from ari_sfm.body.dots import dot_diameter_at
from ari_sfm.cli import main
from ari_sfm.detection import ensure_observations
from ari_sfm.io import load_dataset, save_rig
from ari_sfm.records import CameraSpec, Dataset, Entry
from ari_sfm.simulate.body_images import FRAME, Distractors, cavity_body, cavity_view, render_body_image

BODY = cavity_body()
CLICKED = (2, 3, 71, 73)  # test_cavity's man_ori.par for cam1: the corners of two rows
CLICK_ERROR_PX = 3.0


def _clicks(image, ids=CLICKED, seed=0):
    rng = np.random.default_rng(seed)
    return {int(i): tuple(image.pixels[image.ids == i][0] + rng.uniform(-CLICK_ERROR_PX, CLICK_ERROR_PX, 2))
            for i in ids}


def _window(view) -> BodyWindow:
    plane, iface = view.interface.plane, view.interface
    return BodyWindow(plane.normal, plane.point_mm, iface.thickness_mm, iface.index, iface.medium_index)


def _wrong_ids(image, ids, pixels) -> int:
    """Identified dots nearer another body point's true pixel than their own id's."""
    nearest = np.argmin(np.linalg.norm(image.pixels[None] - pixels[:, None], axis=2), axis=1)
    return int(np.sum(image.ids[nearest] != ids))


@pytest.fixture(scope="module")
def view():
    return cavity_view()


@pytest.fixture(scope="module")
def rendered(view):
    return render_body_image(view, BODY, seed=1)


# ----------------------------------------------------------------------------- dots


def test_dots_are_the_body_dots_not_particles_streak_or_glare(rendered):
    dots = find_dots(rendered.image, DotOptions(diameter_px=float(np.mean(rendered.diameters_px))))
    truth = rendered.pixels[rendered.visible]
    nearest = np.linalg.norm(truth[:, None] - dots.centres[None], axis=2).min(axis=1)
    assert np.mean(nearest < 0.3) >= 0.95  # the body's dots, centred to < 0.3 px
    assert np.all(dots.diameters_px > 0.4 * rendered.diameters_px.mean())  # no speck of the 400 particles
    assert len(dots) < len(truth) + 30  # besides them only the faint reflection's dots and a few strays


def test_dots_of_a_16_bit_image_are_those_of_the_8_bit_one(view):
    eight, sixteen = (render_body_image(view, BODY, seed=2, bit_depth=b) for b in (8, 16))
    assert sixteen.image.dtype == np.uint16 and sixteen.image.max() > 255
    a = find_dots(eight.image, DotOptions(diameter_px=11.0))
    b = find_dots(sixteen.image, DotOptions(diameter_px=11.0))
    assert len(a) == len(b)
    np.testing.assert_allclose(b.centres, a.centres, atol=0.05)  # 12-bit vs 8-bit rounding only


def test_dot_diameter_from_the_clicked_dots(rendered):
    clicked = np.array(list(_clicks(rendered).values()))
    d = dot_diameter_at(rendered.image, clicked, search_px=10.0)
    assert d == pytest.approx(float(np.mean(rendered.diameters_px)), rel=0.15)


# ----------------------------------------------------------------------------- identification


@pytest.mark.parametrize("exact", [False, True], ids=["pinhole", "exact_window"])
def test_identified_ids_are_right_and_nearly_all_found(view, rendered, exact):
    """Zero wrong ids, >= 95 % of the visible points, pixels within 0.3 px of the exact projections."""
    hints = BodyHints(window=_window(view) if exact else None)
    match = find_body(rendered.image, BODY, _clicks(rendered), hints)
    assert _wrong_ids(rendered, match.ids, match.pixels) == 0
    assert len(match.ids) >= 0.95 * rendered.visible.sum()
    err = np.linalg.norm(match.pixels - rendered.pixels[np.searchsorted(rendered.ids, match.ids)], axis=1)
    assert np.sqrt(np.mean(err**2)) < 0.1 and err.max() < 0.3
    if exact:  # the exact model recovers the true focal length from one image
        assert match.camera.focal_px == pytest.approx(view.K[0, 0], rel=0.01)
        assert match.rms_px < 0.1


def test_matching_camera_jacobian_is_the_numerical_one(view):
    """fit_camera's analytic Jacobian (pinhole with k1, and the exact model through the window) against central
    differences, the rotation as a left increment."""
    from ari_sfm.body.camera import MatchCamera, _project
    from ari_sfm.geometry import rotation_from_rotvec

    _, xyz = BODY.points_3d()
    R = view.cam_from_body.R
    params = np.array([0, 0, 0, *view.cam_from_body.t, np.log(5800.0), 650.0, 500.0, 0.3])
    for window in (None, _window(view)):
        camera = MatchCamera(params, aspect=1.02, window=window)
        uv, J = _project(R, params, camera, xyz, jacobian=True)
        assert np.isfinite(uv).all()
        numeric = np.empty_like(J)
        for k in range(10):
            step = np.zeros(10)
            step[k] = 1e-6
            plus = _project(rotation_from_rotvec(step[:3]) @ R, params + step, camera, xyz, jacobian=False)[0]
            minus = _project(rotation_from_rotvec(-step[:3]) @ R, params - step, camera, xyz, jacobian=False)[0]
            numeric[:, :, k] = (plus - minus) / 2e-6
        np.testing.assert_allclose(J, numeric, atol=1e-5 * np.abs(numeric).max())


def test_a_stray_dot_beside_a_body_dot_leaves_that_point_out(view):
    image = render_body_image(view, BODY, distractors=Distractors(beside=(37, 12)), seed=3)
    match = find_body(image.image, BODY, _clicks(image, seed=3))
    assert {37, 12} <= set(match.ambiguous) and not {37, 12} & set(match.ids.tolist())
    assert _wrong_ids(image, match.ids, match.pixels) == 0
    assert len(match.ids) >= 0.95 * (image.visible.sum() - 2)


def _corners(c: dict) -> dict:
    return {k: c[k] for k in CLICKED}


WRONG_CLICK = "do not fit the body|wrong id or pixel|a wrong id among the clicks"  # whichever check sees it first


@pytest.mark.parametrize("change, message", [
    (lambda c: {**{k: c[k] for k in (2, 3, 71)}, 68: c[73]}, WRONG_CLICK),  # id 73 typed as 68
    (lambda c: {**_corners(c), 71: (c[71][0] + 40.0, c[71][1])}, WRONG_CLICK),  # a pixel 40 px off
    (lambda c: {2: c[3], 3: c[2], 71: c[71], 73: c[73]}, WRONG_CLICK),  # two ids swapped
    (lambda c: {**_corners(c), 37: c[61]}, WRONG_CLICK),  # a fifth click on another point's dot
    (lambda c: {k: c[k] for k in (71, 72, 66, 61)}, "lie close together or nearly on a line"),  # one corner only
])
def test_bad_clicks_are_one_clear_error(rendered, change, message):
    """A wrong id or pixel among the clicks is an error, never a wrong identification."""
    clicks = _clicks(rendered, ids=(2, 3, 71, 73, 72, 66, 61))
    with pytest.raises(ClickError, match=message) as err:
        find_body(rendered.image, BODY, change(clicks))
    assert "\n" not in str(err.value)


# ----------------------------------------------------------------------------- datasets


def _dataset(tmp_path: Path, clicks_for=("cam1", "cam2"), bad_click: bool = False,
             focal_px: float | None = None) -> tuple[Path, dict]:
    """Two cameras' rendered images, rig.yaml with the window's plane and the clicks; returns the truth."""
    views = {"cam1": cavity_view(), "cam2": cavity_view((-118.0, 27.0, -578.0), roll_deg=-1.5)}
    tmp_path.mkdir(parents=True)
    images, clicks, truth = {}, {}, {}
    for k, (name, view) in enumerate(views.items()):
        image = render_body_image(view, BODY, seed=10 + k)
        assert cv2.imwrite(str(tmp_path / f"{name}.png"), image.image)
        images[name], truth[name] = tmp_path / f"{name}.png", image
        if name in clicks_for:
            clicks[name] = {i: tuple(map(float, uv)) for i, uv in _clicks(image, seed=k).items()}
    if bad_click:
        clicks["cam2"][68] = clicks["cam2"].pop(73)
    ds = Dataset(root=tmp_path, rig_path=tmp_path / "rig.yaml", target=BODY, interface=views["cam1"].interface,
                 cameras={n: CameraSpec(n, (1280, 1024), focal_px=focal_px) for n in views},
                 calibration=(Entry("calibration", FRAME, images, manual_points=clicks),))
    return save_rig(tmp_path / "rig.yaml", ds), truth


def test_detect_identifies_a_body_from_its_images_and_clicks(tmp_path):
    rig, truth = _dataset(tmp_path / "ds")
    r = CliRunner().invoke(main, ["detect", str(rig.parent), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    records = json.loads((tmp_path / "out" / "observations.json").read_text())["observations"]
    assert [o["camera"] for o in records] == ["cam1", "cam2"]
    for o in records:
        image = truth[o["camera"]]
        ids, pixels = np.array(o["ids"]), np.array(o["pixels"])
        assert _wrong_ids(image, ids, pixels) == 0 and len(ids) >= 0.95 * image.visible.sum()
        assert np.abs(pixels - image.pixels[np.searchsorted(image.ids, ids)]).max() < 0.3
    dataset = ensure_observations(load_dataset(rig))  # what calibrate does with it
    assert [len(o.ids) for o in dataset.observations] == [len(o["ids"]) for o in records]


@pytest.mark.parametrize("clicks_for, bad_click, message", [
    (("cam1",), False, "calibration frame f000: camera cam2: a 3D body (target points3d) is identified in its image "
                       "from >= 4 clicked points: give them as manual_points.cam2"),
    (("cam1", "cam2"), True, "calibration frame f000, manual_points.cam2: the clicked points lead to a camera that "
                             "explains only"),
])
def test_a_body_without_good_clicks_is_one_error_naming_rig_and_camera(tmp_path, clicks_for, bad_click, message):
    rig, _ = _dataset(tmp_path / "ds", clicks_for, bad_click)
    r = CliRunner().invoke(main, ["detect", str(rig.parent), "-o", str(tmp_path / "out")])
    error = r.output.splitlines()[-1]  # after detect's progress bar
    assert r.exit_code == 1 and r.output.count("error:") == 1 and error.startswith(f"error: {rig}: {message}"), r.output
    assert not (tmp_path / "out").exists()


def test_calibrate_from_images_and_clicks(tmp_path):
    """calibrate on images and clicks alone (the window's plane declared, a nominal focal length as a shallow
    body's single view needs): the true focal length and principal point."""
    from ari_sfm.io import load_calibration

    rig, _ = _dataset(tmp_path / "ds", focal_px=5800.0)
    r = CliRunner().invoke(main, ["calibrate", str(rig.parent), "-o", str(tmp_path / "cal")])
    assert r.exit_code == 0, r.output
    cal = load_calibration(tmp_path / "cal" / "calibration.json")
    truth = cavity_view().K
    for camera in cal.cameras.values():
        assert camera.K[0, 0] == pytest.approx(truth[0, 0], rel=3e-3)
        np.testing.assert_allclose(camera.K[:2, 2], truth[:2, 2], atol=5.0)
    assert cal.residuals.rmse_px < 0.1
