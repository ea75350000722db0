"""The closed-form start of a camera (ari_sfm.init.zhang.calibrate_zhang): Zhang's K from the
views' homographies and PnP per view, without an iterative calibration, on a pinhole camera
(no window) whose truth is known."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from ari_sfm.geometry import rotation_from_rotvec
from ari_sfm.init.zhang import calibrate_zhang, object_points
from ari_sfm.records import CameraSpec, Observation, Target

K_TRUE = np.array([[3478.0, 0.0, 1180.5], [0.0, 3471.0, 1050.2], [0.0, 0.0, 1.0]])
SIZE = (2448, 2048)


def views(sigma_px: float, seed: int = 0) -> tuple[Target, list[Observation], dict[str, tuple[np.ndarray, np.ndarray]]]:
    """Twelve tilted views of a 11 x 8 checkerboard at ~450 mm, pixels with ``sigma_px`` noise."""
    rng = np.random.default_rng(seed)
    target = Target(type="checkerboard", square_mm=10.0, inner_corners=(11, 8))
    ids = np.arange(88)
    X = object_points(target, ids)
    obs, truth = [], {}
    for k in range(12):
        R = rotation_from_rotvec(np.radians(rng.uniform(-25, 25, 3)) * [1, 1, 0.3])
        t = np.array([rng.uniform(-40, 40) - 50, rng.uniform(-30, 30) - 35, rng.uniform(400, 500)])
        uv = cv2.projectPoints(X, cv2.Rodrigues(R)[0], t, K_TRUE, None)[0].reshape(-1, 2)
        obs.append(Observation("cam0", "calibration", f"f{k:02d}", ids, uv + rng.normal(0, sigma_px, uv.shape)))
        truth[f"f{k:02d}"] = (R, t)
    return target, obs, truth


def test_noise_free_views_give_the_true_camera():
    target, obs, truth = views(0.0)
    z = calibrate_zhang(target, CameraSpec("cam0", SIZE), obs)
    # exact up to cv2.findHomography's own convergence (~3e-7 relative in the focal length)
    assert np.allclose(z.K, K_TRUE, rtol=1e-6, atol=1e-3)
    assert np.all(z.dist == 0) and z.rms_px < 1e-4
    for frame, (R, t) in truth.items():
        pose = z.cam_from_target[frame]
        assert np.abs(pose.R - R).max() < 1e-6 and np.abs(pose.t - t).max() < 1e-3


def test_noisy_views_give_a_start_near_the_truth_and_a_hint_is_kept():
    target, obs, _ = views(0.1)
    z = calibrate_zhang(target, CameraSpec("cam0", SIZE), obs)
    assert z.K[0, 0] == pytest.approx(K_TRUE[0, 0], rel=0.02) and z.K[1, 1] == pytest.approx(K_TRUE[1, 1], rel=0.02)
    assert abs(z.K[0, 2] - K_TRUE[0, 2]) < 60 and abs(z.K[1, 2] - K_TRUE[1, 2]) < 60
    assert z.rms_px < 3.0  # a start: the bundle adjustment refines it
    hinted = calibrate_zhang(target, CameraSpec("cam0", SIZE, K=K_TRUE * 1.01 + np.diag([0, 0, -0.01])), obs)
    assert np.array_equal(hinted.K, K_TRUE * 1.01 + np.diag([0, 0, -0.01]))  # a K hint is taken as given


def test_the_start_on_two_threads_is_the_start_on_one():
    target, obs, _ = views(0.1, seed=3)
    one, two = calibrate_zhang(target, CameraSpec("cam0", SIZE), obs), \
        calibrate_zhang(target, CameraSpec("cam0", SIZE), obs, threads=2)
    assert np.array_equal(one.K, two.K) and one.rms_px == two.rms_px
    for frame, pose in one.cam_from_target.items():
        other = two.cam_from_target[frame]
        assert np.array_equal(pose.R, other.R) and np.array_equal(pose.t, other.t)


def test_shared_map_keeps_the_order_shares_the_work_and_raises_the_first_failure():
    import threading
    import time

    from ari_sfm.helper_thread import shared_map

    ran_on = {}

    def square(x: int) -> int:
        ran_on[x] = threading.current_thread().name
        time.sleep(0.005)  # releases the GIL, as OpenCV's calls do
        if x in (5, 7):
            raise ValueError(f"item {x}")
        return x * x

    assert shared_map(square, [0, 1, 2, 3, 4, 6, 8, 9], threads=2) == [0, 1, 4, 9, 16, 36, 64, 81]
    assert len(set(ran_on.values())) == 2 and ran_on[0] == threading.current_thread().name
    ran_on.clear()
    assert shared_map(square, [1, 2, 3], threads=2) == [1, 4, 9]  # too few to share
    assert set(ran_on.values()) == {threading.current_thread().name}
    # failures: the first in the items' order raises, whichever thread met it and whenever
    for items, first in (([0, 1, 2, 3, 4, 5, 6, 7], 5), ([5, 0, 1, 2, 7, 3], 5), ([0, 1, 2, 3, 7, 4, 5], 7)):
        ran_on.clear()
        with pytest.raises(ValueError, match=f"item {first}"):
            shared_map(square, items, threads=2)
        assert set(ran_on) == set(items)  # every item ran


def _split_squares(_: int) -> list[int]:
    from ari_sfm.helper_thread import shared_map

    return shared_map(lambda x: x * x, list(range(6)), threads=2)


def test_shared_map_works_in_a_forked_child_of_a_process_that_used_its_pool():
    import multiprocessing

    from ari_sfm.helper_thread import shared_map

    assert shared_map(lambda x: x + 1, [0, 1, 2, 3], threads=2) == [1, 2, 3, 4]  # the parent's pool exists
    with multiprocessing.get_context("fork").Pool(1) as pool:  # the child has none of its threads
        assert pool.apply_async(_split_squares, (0,)).get(timeout=20) == [0, 1, 4, 9, 16, 25]


def test_shared_map_leaves_no_thread_that_would_hold_the_exit_and_never_waits_for_a_busy_helper():
    import threading

    from ari_sfm.helper_thread import helper_thread, shared_map

    assert shared_map(lambda x: -x, [1, 2, 3, 4], threads=2) == [-1, -2, -3, -4]
    me = threading.current_thread()
    # the CLI leaves by os._exit on Ctrl-C while a non-daemon thread lives (cli.process._exit_interrupted)
    assert all(t.daemon for t in threading.enumerate() if t is not me and t.name == "ari-helper")
    release, busy_done = threading.Event(), threading.Event()

    def busy() -> None:  # the helper busy elsewhere, until released (or 30 s)
        release.wait(30)
        busy_done.set()

    helper_thread().run(busy)
    ran_on = []
    assert shared_map(lambda x: ran_on.append(threading.current_thread()) or x, [1, 2, 3, 4], threads=2) == [1, 2, 3, 4]
    assert not busy_done.is_set() and set(ran_on) == {me}  # done alone, not waiting: its helper task dropped
    release.set()


def test_object_points_are_the_targets_rows_and_unknown_ids_raise():
    from ari_sfm.simulate import make_scene

    board = make_scene("paper_single", seed=0).dataset.target
    ids, xyz = board.points_3d()
    assert board.ids_are_rows
    np.testing.assert_array_equal(object_points(board, [5, 0, 87]), xyz[[5, 0, 87]])
    for bad in ([-1, 3], [0, len(ids)]):  # a negative id must not wrap around to the last rows
        with pytest.raises(KeyError):
            object_points(board, np.array(bad))
    body = Target(type="points3d", points={10: (0.0, 0.0, 0.0), 12: (1.0, 2.0, 3.0), 30: (4.0, 5.0, 6.0)})
    assert not body.ids_are_rows
    np.testing.assert_array_equal(object_points(body, [30, 10]), [[4.0, 5.0, 6.0], [0.0, 0.0, 0.0]])
    with pytest.raises(KeyError):
        object_points(body, [11])
