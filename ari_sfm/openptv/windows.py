"""Which window each camera of an OpenPTV experiment looks through (DATASET_FORMAT 1.3).

OpenPTV gives every camera its own glass vector (its ``.ori``'s last line, from the water toward the
camera, its length the distance of the glass-water face from the origin). Cameras behind one wall have
parallel glass vectors; cameras behind another wall (test_cavity's opposite one) point elsewhere.

- With every ``.ori``: :func:`windows_from_glass` groups the cameras whose glass vectors are parallel
  (within :data:`SAME_WINDOW_DEG`) and declares each window's plane from its first camera's vector, held,
  or as a prior with the spread of its cameras' vectors when they differ.
- Without them: :func:`windows_from_axes` groups the cameras by their optical axes in the body's frame
  (resected from the clicked points): cameras looking into the tank from one side are behind one wall.
  Average-linkage clusters of axes closer than :data:`SAME_SIDE_DEG`; the planes are left for calibrate
  to estimate. ``windows`` of :func:`read_experiment` (``--windows`` of ``import openptv``) overrides it.
"""
from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from ari_sfm.errors import AriSfmError
from ari_sfm.records import Interface, Window, WindowPlane

from .conventions import window_plane

log = logging.getLogger(__name__)

SAME_WINDOW_DEG = 5.0  # glass vectors this close in direction: one window
# relative: a window's cameras whose glass vectors differ more get a plane prior, not a fixed plane
GLASS_TOLERANCE = 1e-9
SAME_SIDE_DEG = 70.0  # optical axes (average linkage) closer than this look in through one wall
AMBIGUOUS_RATIO = 1.5  # a grouping whose closest other-wall axes are not this much farther apart than the
# farthest same-wall ones is said to be a guess


def _plate(thickness_mm: float, index: float, medium_index: float, plane: WindowPlane | None = None) -> Interface:
    return Interface(thickness_mm=thickness_mm, index=index, medium_index=medium_index, plane=plane)


def _name(direction: np.ndarray) -> str:
    """A window's name from the direction its cameras look from (the glass vector's or the mean reversed axis):
    ``minus_z`` for cameras on the -z side of the body."""
    k = int(np.argmax(np.abs(direction)))
    return f"{'plus' if direction[k] > 0 else 'minus'}_{'xyz'[k]}"


def _named(groups: list[tuple[list[str], np.ndarray]]) -> list[str]:
    """Distinct names for groups of cameras (their side, numbered when two share one)."""
    names = [_name(d) for _, d in groups]
    return [n if names.count(n) == 1 else f"{n}_{names[:k + 1].count(n)}" for k, n in enumerate(names)]


def windows_from_glass(names: Sequence[str], glasses: Sequence[np.ndarray], ori_paths: Sequence[Path],
                       thickness_mm: float, index: float, medium_index: float, frame: str) -> tuple[Window, ...]:
    """Group cameras with ``.ori`` glass vectors into windows (see the module docstring).

    Args:
        names: the camera names.
        glasses: each camera's glass vector, (3,) mm, in OpenPTV's world.
        ori_paths: each camera's ``.ori`` file, for error messages.
        thickness_mm: the glass thickness.
        index: the glass's refractive index.
        medium_index: the medium's refractive index.
        frame: the target frame the planes are declared in (the calibration frame whose target coordinates
            are OpenPTV's world).

    Returns:
        The windows, each with its declared plane (fixed, or a prior when its cameras' vectors differ).

    Raises:
        AriSfmError: a glass vector is zero.
    """
    groups: list[tuple[list[int], np.ndarray]] = []
    for k, (glass, path) in enumerate(zip(glasses, ori_paths)):
        if not np.linalg.norm(glass) > 0:
            raise AriSfmError(path, "glass vector is zero: OpenPTV needs it to place the window")
        unit = glass / np.linalg.norm(glass)
        for members, direction in groups:
            if np.degrees(np.arccos(np.clip(unit @ direction, -1.0, 1.0))) <= SAME_WINDOW_DEG:
                members.append(k)
                break
        else:
            groups.append(([k], unit))
    windows = []
    labels = _named([([names[k] for k in m], d) for m, d in groups])
    for label, (members, _) in zip(labels, groups):
        planes = [window_plane(glasses[k], thickness_mm) for k in members]
        normal, point = planes[0]
        angles = [np.degrees(np.arccos(np.clip(n @ normal, -1, 1))) for n, _ in planes]
        offsets = [abs(normal @ (p - point)) for _, p in planes]
        sigma_deg, sigma_mm = max(angles), max(offsets)
        scale = max(1.0, float(np.linalg.norm(glasses[members[0]])))
        if sigma_deg <= np.degrees(GLASS_TOLERANCE) and sigma_mm <= GLASS_TOLERANCE * scale:
            sigma_deg = sigma_mm = 0.0
        else:
            log.warning("cameras %s: their glass vectors differ (up to %.3g deg, %.3g mm): the window's plane is "
                        "%s's, as a prior with those sigmas", ", ".join(names[k] for k in members), sigma_deg,
                        sigma_mm, names[members[0]])
        plane = WindowPlane(frame, normal, point, float(sigma_deg), float(sigma_mm))
        windows.append(Window(label, _plate(thickness_mm, index, medium_index, plane),
                              tuple(names[k] for k in members)))
    if len(windows) > 1:
        log.info("%d windows from the glass vectors: %s", len(windows),
                 "; ".join(f"{w.name}: {', '.join(w.cameras)}" for w in windows))
    return tuple(windows)


def windows_from_axes(names: Sequence[str], axes: Sequence[np.ndarray], thickness_mm: float, index: float,
                      medium_index: float) -> tuple[Window, ...]:
    """Group cameras into windows by their optical axes in the body's frame (see the module docstring).

    Average linkage over the angles between axes, merged while closer than :data:`SAME_SIDE_DEG`; a
    warning is logged when the grouping is not clear-cut.

    Args:
        names: the camera names.
        axes: each camera's optical axis, (3,), in the body's frame.
        thickness_mm: the glass thickness.
        index: the glass's refractive index.
        medium_index: the medium's refractive index.

    Returns:
        The windows, their planes left for calibrate to estimate.
    """
    units = [np.asarray(a, float) / np.linalg.norm(a) for a in axes]
    angle = np.degrees(np.arccos(np.clip(np.array([[a @ b for b in units] for a in units]), -1.0, 1.0)))
    clusters = [[k] for k in range(len(units))]
    while len(clusters) > 1:
        best: tuple[float, int, int] | None = None
        for i in range(len(clusters)):
            for j in range(i + 1, len(clusters)):
                d = float(np.mean(angle[np.ix_(clusters[i], clusters[j])]))
                if best is None or d < best[0]:
                    best = (d, i, j)
        if best is None or best[0] >= SAME_SIDE_DEG:
            break
        _, i, j = best
        clusters[i] += clusters.pop(j)
    clusters = sorted((sorted(c) for c in clusters), key=min)
    within = max((angle[a, b] for c in clusters for a in c for b in c), default=0.0)
    between = min((angle[a, b] for c in clusters for d in clusters if c is not d for a in c for b in d), default=180.0)
    if len(clusters) > 1 and between < AMBIGUOUS_RATIO * within:
        log.warning("the cameras' windows are a guess from their viewing directions (cameras of different groups "
                    "%.0f deg apart, of one group up to %.0f deg): check them, or give them (--windows)", between,
                    within)
    groups = [([names[k] for k in c], -np.mean([units[k] for k in c], axis=0)) for c in clusters]
    labels = _named(groups)
    windows = tuple(Window(label, _plate(thickness_mm, index, medium_index), tuple(members))
                    for label, (members, _) in zip(labels, groups))
    log.info("%d window(s) from the cameras' viewing directions: %s", len(windows),
             "; ".join(f"{w.name}: {', '.join(w.cameras)}" for w in windows))
    return windows


def parse_window_groups(text: str, names: Sequence[str], where: str = "--windows") -> list[list[str]]:
    """Parse ``cam1,cam2;cam3,cam4`` as groups of camera names.

    Args:
        text: the groups, separated by ``;``, cameras by ``,``.
        names: the experiment's cameras; each must appear exactly once.
        where: the option named in error messages.

    Returns:
        The groups of camera names.

    Raises:
        AriSfmError: an unknown camera, a camera in no group or in two, or no group.
    """
    groups = [[c.strip() for c in part.split(",") if c.strip()] for part in text.split(";") if part.strip()]
    listed = [c for g in groups for c in g]
    unknown = [c for c in listed if c not in names]
    if unknown:
        raise AriSfmError(where, f"camera {unknown[0]} is not a camera of the experiment ({', '.join(names)})")
    missing = [c for c in names if c not in listed]
    twice = {c for c in listed if listed.count(c) > 1}
    if missing or twice or not groups:
        what = f"camera {missing[0]} is in no group" if missing else f"camera {sorted(twice)[0]} is in two groups"
        raise AriSfmError(where, f"{what if groups else 'no group'}: give every camera once, groups separated by "
                                 "';' (e.g. cam1,cam2;cam3,cam4)")
    return groups


def windows_from_groups(groups: Sequence[Sequence[str]], thickness_mm: float, index: float, medium_index: float
                        ) -> tuple[Window, ...]:
    """Make the windows a user gave (``--windows``), named window1, window2, ...

    Args:
        groups: the cameras behind each window.
        thickness_mm: the glass thickness.
        index: the glass's refractive index.
        medium_index: the medium's refractive index.

    Returns:
        The windows, their planes left for calibrate to estimate.
    """
    return tuple(Window(f"window{k + 1}", _plate(thickness_mm, index, medium_index), tuple(g))
                 for k, g in enumerate(groups))
