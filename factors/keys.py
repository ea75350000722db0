"""Variable keys of the rig factor graph, stated once.

- K(c): intrinsics of camera c, a Vector [fx, fy, cx, cy(, k1, k2, p1, p2, k3)]
- C(c): world_T_cam of camera c (GTSAM convention; camera 0 is the world, no variable)
- N: the window normal in the world frame, a Unit3 shared by every camera
- X(f): world_T_target of target frame f (calibration frames and stacking poses)
- H: distance (mm) from camera 0's centre to the window's near surface, a Vector1
"""
from __future__ import annotations

import gtsam


def K(camera_index: int) -> int:
    return gtsam.symbol("k", camera_index)


def C(camera_index: int) -> int:
    return gtsam.symbol("c", camera_index)


def X(frame_index: int) -> int:
    return gtsam.symbol("x", frame_index)


N = gtsam.symbol("n", 0)
H = gtsam.symbol("h", 0)
