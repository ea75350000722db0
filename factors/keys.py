"""Variable keys of the rig factor graph, stated once.

- K(c): intrinsics of camera c, a Vector [fx, fy, cx, cy(, k1, k2, p1, p2, k3)]
- C(c): world_T_cam of camera c (GTSAM convention; camera 0 is the world, no variable)
- N(w): the normal of window w in the world frame, a Unit3 shared by the cameras behind it
  (``N`` = N(0): the window of a one-window rig)
- X(f): world_T_target of target frame f (calibration frames and stacking poses)
- H(w): window w's near face as the world plane ``N(w) . X = H(w)`` (mm), a Vector1; for the window
  of camera 0 (the world's origin) the distance from camera 0's centre (``H`` = H(0))

The points problem of refine-colmap and self-calibration (:mod:`ari_sfm.colmap.refine.gtsam_graph`) uses
K(c) and N(w) as above and:

- F(k): rig_from_world of frame k (a Pose3; frame 0 is the gauge, no variable)
- S(c): sensor_from_rig of camera c (a Pose3; the reference sensors have none)
- D(w): window w's distance (a Vector1)
- P(j): a 3D point (a Point3)
"""
from __future__ import annotations

import gtsam


def K(camera_index: int) -> int:
    return gtsam.symbol("k", camera_index)


def C(camera_index: int) -> int:
    return gtsam.symbol("c", camera_index)


def X(frame_index: int) -> int:
    return gtsam.symbol("x", frame_index)


def window_normal(window_index: int) -> int:
    """N(w): window w's normal."""
    return gtsam.symbol("n", window_index)


def window_plane(window_index: int) -> int:
    """H(w): window w's near face offset."""
    return gtsam.symbol("h", window_index)


N = window_normal(0)
H = window_plane(0)


def rig_frame(frame_index: int) -> int:
    """F(k): the points problem's rig_from_world of frame k."""
    return gtsam.symbol("f", frame_index)


def sensor(camera_index: int) -> int:
    """S(c): the points problem's sensor_from_rig of camera c."""
    return gtsam.symbol("s", camera_index)


def window_distance(window_index: int) -> int:
    """D(w): the points problem's window distance."""
    return gtsam.symbol("d", window_index)


def point(point_index: int) -> int:
    """P(j): the points problem's 3D point j."""
    return gtsam.symbol("p", point_index)
