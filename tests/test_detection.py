"""Corner detection on rendered boards, compared with the exact rendered corners (ari_sfm.simulate.render).

Measured on these 640 x 480 views (square ~20-30 px, 1 grey level noise):
checkerboard subpix ~0.025 px RMS, findChessboardCornersSB ~0.08-0.15 px,
ChArUco ~0.06 px (OpenCV's own corners ~0.10 px).
"""
from __future__ import annotations

import logging

import cv2
import numpy as np
import pytest
import yaml
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.detection import checkerboard_ids_unambiguous, detect_corners, detect_dataset
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.io import load_dataset
from ari_sfm.records import Target
from ari_sfm.simulate.render import plane_pixel_to_target, project_pinhole, render_target

W, H = 640, 480
K = np.array([[800.0, 0, (W - 1) / 2], [0, 800.0, (H - 1) / 2], [0, 0, 1.0]])
CHECKER = Target(type="checkerboard", square_mm=10.0, inner_corners=(11, 8))
CHARUCO = Target(type="charuco", square_mm=10.0, squares=(8, 6), marker_mm=7.5, dictionary="DICT_5X5_100")


def render(target, roll_deg, tilt_deg=(15.0, -10.0), square_px=28.0, seed=0, blur=0.0, shift=(3.0, -2.0)):
    """(image, exact pixels of every id) of a pinhole view of ``target``."""
    _, xyz = target.points_3d()
    dist = K[0, 0] * target.square_mm / square_px
    R = rotation_from_rotvec(np.deg2rad([tilt_deg[0], tilt_deg[1], 0.0])) @ rotation_from_rotvec(
        np.array([0.0, 0.0, np.deg2rad(roll_deg)]))
    t = np.array([shift[0], shift[1], dist]) - R @ xyz.mean(axis=0)
    image = render_target(target, plane_pixel_to_target(K, R, t), (W, H), supersample=4, noise_sigma=1.0,
                          seed=seed, blur_sigma_px=blur)
    return image, project_pinhole(K, R, t, xyz)


def rms(err):
    return float(np.sqrt(np.mean(np.sum(np.asarray(err) ** 2, axis=-1))))


# rolls 0/90/180/270 (OpenCV returns the grid in different orders), an oblique one, a blurred one
CHECKER_VIEWS = [(0, (15, -10), 0.0), (90, (15, -10), 0.0), (180, (15, -10), 0.0), (270, (15, -10), 0.0),
                 (33, (35, 20), 0.0), (200, (-25, 10), 0.7)]


@pytest.fixture(scope="module")
def checker_views():
    return [render(CHECKER, roll, tilt, seed=k, blur=blur) for k, (roll, tilt, blur) in enumerate(CHECKER_VIEWS)]


@pytest.fixture(scope="module")
def charuco_views():
    spec = [(0, (15, -10), 40), (180, (15, -10), 25), (75, (-20, 25), 30), (300, (30, 5), 20)]
    return [render(CHARUCO, roll, tilt, square_px=sp, seed=k) for k, (roll, tilt, sp) in enumerate(spec)]


# --------------------------------------------------------------------------- checkerboard


def test_checkerboard_corners_match_the_rendered_corners(checker_views):
    """Default detector (findChessboardCorners + cornerSubPix): every id, ~0.025 px RMS, no bias."""
    errors = []
    for (image, exact), (roll, _, _) in zip(checker_views, CHECKER_VIEWS):
        found = detect_corners(image, CHECKER)
        assert found is not None, roll
        ids, pixels = found
        assert np.array_equal(ids, np.arange(88)), roll  # id = r * cols + c, every corner
        err = pixels - exact[ids]
        assert rms(err) < 0.05 and np.abs(err).max() < 0.15, (roll, rms(err))
        errors.append(err)
    e = np.concatenate(errors)
    assert rms(e) < 0.04  # measured 0.025
    assert np.abs(e.mean(axis=0)).max() < 0.01  # no systematic shift (e.g. a half-pixel convention error)


def test_subpix_beats_findChessboardCornersSB(checker_views):
    """The default is the most accurate variant on the same images (as the module docstring claims)."""
    out = {}
    for method in ("subpix", "sb", "classic"):
        errors = []
        for image, exact in checker_views:
            found = detect_corners(image, CHECKER, method=method)
            assert found is not None, method
            ids, pixels = found
            assert np.array_equal(ids, np.arange(88)), method  # same contract ids whatever the detector
            errors.append(pixels - exact[ids])
        out[method] = rms(np.concatenate(errors))
    assert out["subpix"] < 0.04 and out["sb"] < 0.3 and out["classic"] < 0.3, out
    assert out["subpix"] < 0.5 * out["sb"] and out["subpix"] < 0.5 * out["classic"], out  # measured ~0.025 vs ~0.12


def test_ids_follow_the_contract_and_survive_image_rotations(checker_views):
    """id = r * cols + c: id 1 is one step along board x from id 0, id cols one step along y; and
    rotating the image by 90/180/270 degrees gives the same ids at the same corners (11 + 8 is odd)."""
    assert checkerboard_ids_unambiguous(CHECKER)
    image, exact = checker_views[4]
    ids, pixels = detect_corners(image, CHECKER)
    g = pixels.reshape(8, 11, 2)
    assert np.linalg.norm(g[0, 1] - exact[1]) < 0.2 and np.linalg.norm(g[1, 0] - exact[11]) < 0.2
    back = {  # rotated pixel -> original pixel
        cv2.ROTATE_180: lambda p: np.stack([W - 1 - p[:, 0], H - 1 - p[:, 1]], axis=1),
        cv2.ROTATE_90_CLOCKWISE: lambda p: np.stack([p[:, 1], H - 1 - p[:, 0]], axis=1),
        cv2.ROTATE_90_COUNTERCLOCKWISE: lambda p: np.stack([W - 1 - p[:, 1], p[:, 0]], axis=1),
    }
    for code, to_original in back.items():
        found = detect_corners(cv2.rotate(image, code), CHECKER)
        assert found is not None, code
        rids, rpix = found
        assert np.array_equal(rids, ids), code
        assert np.abs(to_original(rpix) - pixels).max() < 0.02, code  # the same corner under each id


def test_symmetric_board_is_flagged_and_still_found():
    """cols + rows even: a 180 degree turn looks the same, so the ids are either the truth or reversed."""
    assert not checkerboard_ids_unambiguous(Target(type="checkerboard", square_mm=10.0, inner_corners=(10, 8)))
    assert not checkerboard_ids_unambiguous(Target(type="checkerboard", square_mm=10.0, inner_corners=(7, 7)))
    assert checkerboard_ids_unambiguous(Target(type="checkerboard", square_mm=10.0, inner_corners=(9, 6)))
    board = Target(type="checkerboard", square_mm=10.0, inner_corners=(10, 8))
    for roll in (0, 180):
        image, exact = render(board, roll, seed=roll)
        ids, pixels = detect_corners(image, board)
        assert np.array_equal(ids, np.arange(80))
        err = min(rms(pixels - exact), rms(pixels[::-1] - exact))
        assert err < 0.05, roll


def test_no_target_or_cut_board_returns_none(checker_views):
    rng = np.random.default_rng(0)
    blank = np.full((H, W), 128, np.uint8)
    noise = np.clip(128 + 40 * rng.standard_normal((H, W)), 0, 255).astype(np.uint8)
    for image in (blank, noise):
        for method in ("subpix", "sb"):
            assert detect_corners(image, CHECKER, method=method) is None
        assert detect_corners(image, CHARUCO) is None
    image, exact = checker_views[0]
    cut = image.copy()
    cut[:, int(exact[:, 0].mean()):] = 128  # right half of the board gone: not a full grid
    assert detect_corners(cut, CHECKER) is None
    with pytest.raises(ValueError, match="unknown checkerboard method"):
        detect_corners(image, CHECKER, method="nope")


def test_colour_and_16_bit_images_give_the_same_corners(checker_views):
    image, _ = checker_views[0]
    ids, pixels = detect_corners(image, CHECKER)
    for variant in (cv2.cvtColor(image, cv2.COLOR_GRAY2BGR), image.astype(np.uint16) * 257):
        vids, vpix = detect_corners(variant, CHECKER)
        assert np.array_equal(vids, ids) and np.abs(vpix - pixels).max() < 0.05


# --------------------------------------------------------------------------- ChArUco


def test_charuco_corners_and_ids_match_the_truth(charuco_views):
    errors, raw_errors = [], []
    for k, (image, exact) in enumerate(charuco_views):
        ids, pixels = detect_corners(image, CHARUCO)
        assert len(ids) >= 30 and np.all(np.diff(ids) > 0) and ids.min() >= 0 and ids.max() < 35, k
        err = pixels - exact[ids]  # wrong ids would be a square (>= 20 px) off
        assert np.abs(err).max() < 0.5, (k, np.abs(err).max())
        errors.append(err)
        rids, raw = detect_corners(image, CHARUCO, method="charuco_raw")
        assert np.array_equal(rids, ids)
        raw_errors.append(raw - exact[rids])
    e, e_raw = rms(np.concatenate(errors)), rms(np.concatenate(raw_errors))
    assert e < 0.08, e  # measured 0.058
    assert e <= e_raw, (e, e_raw)  # our refinement never makes OpenCV's corners worse (raw: ~0.10)


def test_charuco_partly_hidden_gives_the_visible_corners_with_their_ids(charuco_views):
    image, exact = charuco_views[0]
    hidden = image.copy()
    cut = int(np.median(exact[:, 0]))
    hidden[:, :cut] = 128
    ids, pixels = detect_corners(hidden, CHARUCO)
    assert 8 <= len(ids) < 35
    assert np.all(exact[ids, 0] > cut)  # only corners in the visible part, under their own ids
    assert rms(pixels - exact[ids]) < 0.15


# --------------------------------------------------------------------------- datasets


def write_dataset(root, images, stacking=()):
    """A one-camera dataset in ``root``: calibration frames f000.. from ``images``, optional stacking pairs."""
    (root / "img").mkdir(parents=True)
    rig = {"format": "ari-sfm/1", "target": {"type": "checkerboard", "inner_corners": [11, 8], "square_mm": 10.0},
           "interface": {"thickness_mm": 50.0, "index": 1.5168}, "cameras": {"cam0": {"image_size": [W, H]}},
           "calibration": [], "stacking": []}
    for k, image in enumerate(images):
        cv2.imwrite(str(root / "img" / f"c{k}.png"), image)
        rig["calibration"].append({"frame": f"f{k:03d}", "images": {"cam0": f"img/c{k}.png"}})
    for k, (added, image) in enumerate(stacking):
        cv2.imwrite(str(root / "img" / f"s{k}.png"), image)
        rig["stacking"].append({"pose": "s0", "added_mm": added, "images": {"cam0": f"img/s{k}.png"}})
    if not rig["stacking"]:
        del rig["stacking"]
    (root / "rig.yaml").write_text(yaml.safe_dump(rig, sort_keys=False))
    return root


BLANK = np.full((H, W), 128, np.uint8)


def test_detect_dataset_warns_about_and_skips_an_image_without_target(checker_views, tmp_path, caplog):
    images = [checker_views[0][0], BLANK, checker_views[1][0], checker_views[2][0]]
    stacking = [(0, checker_views[3][0]), (10, BLANK)]  # one thickness left: the pose is dropped
    ds = load_dataset(write_dataset(tmp_path / "ds", images, stacking))
    with caplog.at_level(logging.WARNING, logger="ari_sfm.detection"):
        obs = detect_dataset(ds, workers=2, progress=False)
    warnings = [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]
    assert any("c1.png" in m and "target not found" in m for m in warnings), warnings
    assert any("s1.png" in m for m in warnings) and any("stacking pose s0" in m for m in warnings), warnings
    assert not any("c0.png" in m or "c2.png" in m or "c3.png" in m for m in warnings)
    assert [(o.set, o.frame) for o in obs] == [("calibration", "f000"), ("calibration", "f002"),
                                               ("calibration", "f003")]
    for o, (_image, exact) in zip(obs, [checker_views[0], checker_views[1], checker_views[2]]):
        assert o.camera == "cam0" and np.array_equal(o.ids, np.arange(88))
        assert rms(o.pixels - exact[o.ids]) < 0.05  # PNG round trip changes nothing


def test_too_few_views_is_an_error_naming_the_rig_and_camera(checker_views, tmp_path):
    ds = load_dataset(write_dataset(tmp_path / "ds", [checker_views[0][0], BLANK, checker_views[1][0], BLANK]))
    with pytest.raises(AriSfmError) as info:
        detect_dataset(ds, progress=False)
    assert info.value.path == str(ds.rig_path)
    assert "only 2 of the 4 calibration images of camera cam0" in info.value.message
    assert "need >= 3" in info.value.message
    assert len(detect_dataset(ds, progress=False, min_calibration_views=2)) == 2


@pytest.mark.parametrize("content", [b"", b"not an image" * 20, "truncated"])
def test_unreadable_image_is_an_error_naming_it(checker_views, tmp_path, content):
    """A file that does not decode is a broken dataset, not a view without target: error, not warning."""
    root = write_dataset(tmp_path / "ds", [checker_views[k][0] for k in range(4)])
    if content == "truncated":
        data = (root / "img" / "c2.png").read_bytes()
        content = data[: len(data) // 2]
    (root / "img" / "c2.png").write_bytes(content)
    (root / "img" / "c3.png").write_bytes(b"")  # a second one: the first in dataset order is named
    ds = load_dataset(root)
    with pytest.raises(AriSfmError) as info:
        detect_dataset(ds, workers=2, progress=False)
    assert info.value.path == str(root / "img" / "c2.png")
    assert info.value.message.startswith("cannot read image") and "(and 1 more unreadable images)" in info.value.message


def test_cli_detect_unreadable_image_exits_1_without_writing(checker_views, tmp_path):
    root = write_dataset(tmp_path / "ds", [checker_views[k][0] for k in range(3)])
    (root / "img" / "c1.png").write_bytes(b"garbage")
    r = CliRunner().invoke(main, ["detect", str(root), "-o", str(tmp_path / "out")])
    assert r.exit_code == 1
    assert f"error: {root / 'img' / 'c1.png'}: cannot read image" in r.output
    assert not (tmp_path / "out" / "observations.json").exists()
