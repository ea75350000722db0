"""refine-colmap: a COLMAP (pinhole) reconstruction made behind a flat window, refined with the
exact refractive model.

Start: the model as COLMAP left it, read as its paraxial virtual cameras (the ari model: a camera
behind a plate with a medium n_m sees the scene as a pinhole with focal n_m f whose centre sits
``n_m a`` behind it along the normal, ``a`` the ari model's apparent offset), the window normal on
the optical axis (mount camera) or on the mean viewing direction (mount world), and the distance
found by a search on the cost: for each candidate distance, LM on everything but the window (the
middle candidate from COLMAP's model, up to SEARCH_ITERATIONS; the others warm-started from its
result, WARM_SEARCH_ITERATIONS), the lowest cost wins; then everything is refined (air behind: the distance is
unobservable and held).

Gauge and scale: the first frame's pose is held (the world's rotation and translation). The
scale is *not* a gauge: the plate's thickness in mm sets it through refraction, but only weakly
(a plate a few mm thick against a scene metres away; ``uncertainty.scale_rel`` says how weakly).
The input's units are taken as ``units_mm`` mm each (a start only; ``scale_bar``: its factor;
neither: 1, the model is taken to be in mm, and a scene that would then lie inside the port is
refused with one line). A scale bar is a term of the solver (:mod:`.scale_bar`): the refinement
first runs without it (the scale free, along its near-flat valley), the result is rescaled to
the bar, and the refinement runs again with the bar held; going straight to the held bar left a
short-track strip in a wrong-scale valley (40-image strip: 1.80 px, points 47 mm; this way 0.62 px,
1.2 mm). :mod:`ari_sfm.colmap.refine.problem` lists what is estimated.

A long chain (a strip survey) starts otherwise: :mod:`.chain_start`.

A declared window (``interface.plane``, :mod:`.plane`) replaces the start search: the window
starts there; a sigma of 0 holds that part, > 0 adds a prior (a held plane does not scale with the
scene when the state is rescaled to the bar; the bar, a term of the solver, is held anyway).
"""
from __future__ import annotations

import logging
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from ari_sfm.calibration.origin import RefineColmapFrames
from ari_sfm.calibration.record import Calibration, CameraCalibration
from ari_sfm.colmap import adapter
from ari_sfm.errors import AriSfmError
from ari_sfm.geometry import Pose, rotation_from_rotvec
from ari_sfm.io import save_calibration
from ari_sfm.models import AriModel, PinholeModel
from ari_sfm.records import Interface, WindowPlane

from .chain_start import first_block, slid_start
from .plane import declared_window, window_prior
from .problem import MOUNTS, RefractiveProblem, State
from .report import (
    BaselineReport,
    DeclaredPlaneReport,
    Plate,
    RefineCounts,
    RefineReport,
    Reprojection,
    ScaleBarReport,
    WindowEstimate,
)
from .scale_bar import Baseline, ScaleBar
from .settings import HUBER_PX, MAX_ITERATIONS
from .solver import Solver
from .uncertainty import uncertainty

log = logging.getLogger(__name__)

DISTANCE_CANDIDATES_MM = (10.0, 30.0, 100.0)
SEARCH_ITERATIONS = 10  # the first start distance, window held (LM stops earlier when converged)
WARM_SEARCH_ITERATIONS = 4  # the other start distances, warm-started
SEARCH_RELATIVE_TOLERANCE = 1e-2  # the search's LM stops at a relative decrease below this: it ranks the starts,
#                                   the final refinement converges (28 images: 8 search linearizations instead of 13)
AIR_DISTANCE_MM = 10.0  # held: unobservable in air


@dataclass(frozen=True)
class RefineResult:
    """What :func:`refine_colmap` returns.

    ``reconstruction``: the COLMAP model to hand to COLMAP's tools: the refined 3D points (mm),
    the cameras and poses as their best approximation in COLMAP's camera models (OPENCV by
    default: COLMAP's own bundle adjustment with the points held; the poses are those virtual
    cameras', not the real centres). ``refractive``: the refined model itself (real poses, the lens intrinsics
    behind the window; its cameras are NOT pinhole cameras of the images). ``calibration``: the
    refractive cameras (exact model) with each housing's normal_cam and distance.
    """

    reconstruction: Any
    refractive: Any
    calibration: Calibration
    state: State
    report: RefineReport


def _units_mm(model: adapter.ColmapModel, units_mm: float | None, scale_bar: tuple[int, int, float] | None,
              path: Any, baseline: Baseline | None = None) -> float:
    """mm per unit of the COLMAP model (``path``: the WINDOW.yaml named in errors; ``baseline``: the
    scale from two images' camera centres in the model as COLMAP left it)."""
    if baseline is not None:
        start = _initial_state(model, "camera", 1.0)
        length = baseline.length(start)
        if not length > 0:
            raise AriSfmError(path, f"baseline: images {model.image_names[baseline.a]} and "
                                    f"{model.image_names[baseline.b]} have the same camera centre in the model")
        units = baseline.length_mm / length
    elif scale_bar is not None:
        a, b, mm = scale_bar
        where = {int(p): k for k, p in enumerate(model.point3D_ids)}
        missing = [int(i) for i in (a, b) if int(i) not in where]
        if missing:
            raise AriSfmError(path,
                              f"scale_bar.point3D_ids: {', '.join(map(str, missing))} not in the model's points3D")
        if int(a) == int(b):
            raise AriSfmError(path, "scale_bar.point3D_ids: the two ids are the same point")
        length = float(np.linalg.norm(model.xyz[where[int(a)]] - model.xyz[where[int(b)]]))
        if not length > 0 or not mm > 0:
            raise AriSfmError(path, "scale_bar: its points coincide in the model or its distance_mm is not positive")
        units = mm / length
    elif units_mm is None:
        log.warning("refine-colmap: no units_mm or scale bar: the COLMAP model's units are taken as mm")
        units = 1.0
    elif not units_mm > 0:
        raise AriSfmError(path, f"units_mm must be > 0, got {units_mm}")
    else:
        units = float(units_mm)
    extent = float(np.max(np.abs(model.xyz))) * units
    if not (np.isfinite(units) and np.isfinite(extent) and extent < MAX_COORDINATE_MM):
        what = "baseline" if baseline is not None else "scale_bar" if scale_bar is not None else "units_mm"
        raise AriSfmError(path, f"{what}: {units:.6g} mm per model unit puts the model's points up to {extent:.3g} mm "
                                f"from its origin (more than {MAX_COORDINATE_MM:.0e} mm)")
    return units


def _baseline(model: adapter.ColmapModel, baseline: tuple[str | int, str | int, float], path: Any) -> Baseline:
    """The baseline term of two images named by their names (or COLMAP image ids) and their centres' distance."""
    a, b, mm = baseline
    index = {}
    for name in (a, b):
        hits = np.flatnonzero(model.image_ids == name) if isinstance(name, (int, np.integer)) else \
            [k for k, n in enumerate(model.image_names) if n == str(name)]
        if len(hits) == 0:
            raise AriSfmError(path, f"baseline: image {name} is not among the model's (registered) images")
        index[name] = int(hits[0])
    if index[a] == index[b]:
        raise AriSfmError(path, f"baseline: names image {a} twice (two images are needed)")
    if not (np.isfinite(mm) and mm > 0):
        raise AriSfmError(path, f"baseline: the distance must be a positive number of mm (got {mm})")
    i, j = index[a], index[b]
    return Baseline(i, j, (int(model.image_frame[i]), int(model.image_frame[j])),
                    (int(model.image_camera[i]), int(model.image_camera[j])), float(mm))


def _to_scale(state: State, bar: ScaleBar | None, baseline: Baseline | None, window: bool) -> tuple[State, float]:
    """``state`` rescaled so that its scale bar or baseline has its declared length; the factor."""
    s = (bar.length_mm / bar.length(state.xyz) if bar is not None else
         baseline.length_mm / baseline.length(state) if baseline is not None else 1.0)
    return _scaled(state, s, window), s


MAX_COORDINATE_MM = 1e9  # 1000 km: a units_mm beyond this is a typo
SCENE_CLEARANCE = 0.5  # a start distance's window (plus plate) must be nearer than this times the near points


MODEL_FILES = ("cameras", "images", "points3D")
MIN_REDUNDANCY = 1.5  # observations (coordinates) per unknown below which refine-colmap refuses


def read_model(path: Path) -> Any:
    """A COLMAP model folder as a pycolmap.Reconstruction; one line naming the folder or the file that
    is missing, unreadable or truncated (a binary file must be what pycolmap writes back from it)."""
    import tempfile

    if not path.is_dir():
        raise AriSfmError(path, "not a COLMAP model folder" + (" (it is a file)" if path.exists() else " (missing)"))
    text = (sum((path / f"{n}.txt").exists() for n in MODEL_FILES)
            > sum((path / f"{n}.bin").exists() for n in MODEL_FILES))
    kind = "txt" if text else "bin"
    for n in MODEL_FILES:
        f = path / f"{n}.{kind}"
        if not f.is_file():
            raise AriSfmError(f, "not a file" if f.exists() else
                              "missing: a COLMAP model folder holds cameras, images and points3D (.bin or .txt)")
        if not os.access(path / f"{n}.{kind}", os.R_OK):
            raise AriSfmError(path / f"{n}.{kind}", "no permission to read")
    try:
        rec = adapter.read_colmap(path)
    except AriSfmError:
        raise
    except Exception as exc:  # noqa: BLE001 - pycolmap's reader raises plain errors for damaged files
        why = str(exc).strip().splitlines()[-1] if str(exc).strip() else type(exc).__name__
        raise AriSfmError(path, f"cannot read the COLMAP model (a truncated or damaged file?): {why}") from None
    if kind == "bin":  # a truncated file reads as fewer or garbled records: compare with what they write back
        with tempfile.TemporaryDirectory() as tmp:
            rec.write(tmp)
            for n in MODEL_FILES + ("rigs", "frames"):
                f, back = path / f"{n}.bin", Path(tmp) / f"{n}.bin"
                if f.is_file() and back.is_file() and f.stat().st_size != back.stat().st_size:
                    raise AriSfmError(f, f"truncated or damaged: its {f.stat().st_size} bytes read as records that "
                                         f"take {back.stat().st_size}")
    return rec


def _check_redundancy(model: adapter.ColmapModel, path: Any) -> None:
    """Refuse a model with too few observations for its unknowns (it would "converge" to 0 px)."""
    unknowns = (sum(len(p) for p in model.colmap_params) + 6 * (len(model.frame_ids) - 1) + 3
                + 3 * len(model.point3D_ids))
    coordinates = 2 * len(model.obs_point)
    if coordinates < MIN_REDUNDANCY * unknowns:
        raise AriSfmError(path, f"too few observations to refine: {len(model.point3D_ids)} points3D seen "
                                f"{len(model.obs_point)} times give {coordinates} coordinates for {unknowns} unknowns "
                                f"(cameras, poses, window, points); at least {MIN_REDUNDANCY:g} per unknown needed")


def _check_finite(model: adapter.ColmapModel, path: Any) -> None:
    """One line naming the first point3D, camera or image with a non-finite value."""
    bad = np.flatnonzero(~np.all(np.isfinite(model.xyz), axis=1))
    if len(bad):
        raise AriSfmError(path, f"point3D {int(model.point3D_ids[bad[0]])} has a non-finite position "
                                f"({len(bad)} such points3D)")
    for c, p in enumerate(model.colmap_params):
        if not np.all(np.isfinite(p)):
            raise AriSfmError(path, f"camera {int(model.camera_ids[c])}: non-finite parameters {p.tolist()}")
    for f, pose in enumerate(model.rig_from_world):
        if not (np.all(np.isfinite(pose.R)) and np.all(np.isfinite(pose.t))):
            raise AriSfmError(path, f"frame {int(model.frame_ids[f])}: non-finite pose")
    if not np.all(np.isfinite(model.obs_uv)):
        raise AriSfmError(path, "an image has a non-finite keypoint observed by a point3D")
    size = np.array(model.image_sizes, float)[model.image_camera[model.obs_image]]  # (M, 2) width, height
    outside = np.any((model.obs_uv < -0.5 - EDGE_TOLERANCE_PX) | (model.obs_uv > size - 0.5 + EDGE_TOLERANCE_PX),
                     axis=1)
    if outside.any():
        k = int(np.argmax(outside))
        i = int(model.obs_image[k])
        raise AriSfmError(path, f"image {model.image_names[i]}: a keypoint observed by point3D "
                                f"{int(model.point3D_ids[model.obs_point[k]])} at ({model.obs_uv[k, 0]:.6g}, "
                                f"{model.obs_uv[k, 1]:.6g}) px is outside its {int(size[k, 0])} x {int(size[k, 1])} "
                                f"image ({int(outside.sum())} such observations)")


EDGE_TOLERANCE_PX = 1.0  # a keypoint this far beyond the image's edge is kept (sub-pixel centres)


def _candidates_inside_scene(model: adapter.ColmapModel, state: State, interface: Interface,
                             candidates: tuple[float, ...], units_given: bool, declared: bool,
                             path: Any) -> tuple[float, ...]:
    """The start distances whose window (plus plate) lies well in front of the near points (the 5th
    percentile of the observations' depths): in COLMAP's arbitrary units read as mm a scene can lie
    inside the port; then one line asks for units_mm or a scale bar."""
    R, t = state.cam_from_world(model)
    depth = np.einsum("nj,nj->n", R[model.obs_image, 2, :], state.xyz[model.obs_point]) + t[model.obs_image, 2]
    near = float(np.percentile(depth, 5))
    if not near > 0:
        raise AriSfmError(path, f"most of the COLMAP model's observed points are behind their cameras "
                                f"(5th percentile depth {near:.3g} mm)")
    keep = tuple(h for h in candidates if h + interface.thickness_mm < SCENE_CLEARANCE * near)
    if declared or keep:
        return candidates if declared else keep
    how = ("check units_mm / scale_bar" if units_given else
           "the model is in COLMAP's arbitrary units: give units_mm (mm per model unit) or a scale_bar")
    raise AriSfmError(path, f"the COLMAP model's points are only {near:.3g} mm in front of its cameras (5th "
                            f"percentile, read as mm): a {interface.thickness_mm:g} mm plate {min(candidates):g} mm "
                            f"or more in front of the lens would lie among them; {how}")


SEARCH_OBSERVATIONS = 6_000  # the distance search runs on a subset of the points with about this many observations


def _subsample(model: adapter.ColmapModel, bar: ScaleBar | None, max_observations: int
               ) -> tuple[adapter.ColmapModel, np.ndarray, ScaleBar | None]:
    """The model restricted to every k-th point3D (and the scale bar's two), so that it has about
    ``max_observations`` observations; the kept point indices and the bar re-indexed."""
    M, P = len(model.obs_point), len(model.point3D_ids)
    if M <= max_observations:
        return model, np.arange(P), bar
    step = int(np.ceil(M / max_observations))
    chosen = np.zeros(P, bool)
    chosen[::step] = True
    if bar is not None:
        chosen[[bar.a, bar.b]] = True
    keep = np.flatnonzero(chosen)
    new_index = np.cumsum(chosen) - 1
    obs = chosen[model.obs_point]
    sub = replace(model, point3D_ids=model.point3D_ids[keep], xyz=model.xyz[keep], obs_image=model.obs_image[obs],
                  obs_point=new_index[model.obs_point[obs]], obs_uv=model.obs_uv[obs])
    sub_bar = None if bar is None else ScaleBar(int(new_index[bar.a]), int(new_index[bar.b]), bar.length_mm)
    return sub, keep, sub_bar


FREE_SCALE_FIRST = True  # with a scale bar: refine without it, rescale to it, then refine with it held
DISTANCE_COLLAPSE = 0.1  # a refined distance below this fraction of the smallest start candidate "ran to 0"


def _collapsed(state: State, problem: RefractiveProblem, candidates: tuple[float, ...]) -> bool:
    """The refined window distance ran toward 0 (where the cost is flat the refinement can slide there)."""
    return bool(np.min(problem.image_windows(state)[1]) < DISTANCE_COLLAPSE * min(candidates))


def _distance_search(model: adapter.ColmapModel, problem: RefractiveProblem, interface: Interface, mount: str,
                     estimate_distance: bool, huber_px: float | None, bar: ScaleBar | None, virtual: State,
                     candidates: tuple[float, ...], declared: bool, baseline: Baseline | None = None
                     ) -> tuple[list[dict], tuple[float, State, int], list[tuple[float, State, int]]]:
    """The cost profile over the start distance, everything but the window refined (the window held):
    the middle candidate from COLMAP's model, the others warm-started from its result (moved to their
    distance, paraxially); the lowest cost wins. Returns the profile, the best (cost, state, iterations)
    and the other candidates' ends (cheapest first)."""
    full_xyz, full_model, full_virtual, full_bar = virtual.xyz, model, virtual, bar
    model, keep, bar = _subsample(model, bar, SEARCH_OBSERVATIONS)
    virtual = replace(virtual, xyz=virtual.xyz[keep])
    held = Solver(RefractiveProblem(model, interface, mount, estimate_distance, hold_window=True), huber_px, bar=bar,
                  baseline=baseline)
    sub = RefractiveProblem(model, interface, mount, estimate_distance)
    search: list[dict] = []
    best: tuple[float, State, int] | None = None
    others: list[tuple[float, State, int]] = []
    order = sorted(candidates, key=lambda h: abs(candidates.index(h) - (len(candidates) - 1) / 2))
    warm = None
    for h in order:
        base = virtual if warm is None else warm
        start = _convert(model, sub, base if declared else _with_distance(model, base, mount, h), +1)
        res = held.run(start, SEARCH_ITERATIONS if warm is None else WARM_SEARCH_ITERATIONS,
                       relative_tolerance=SEARCH_RELATIVE_TOLERANCE)
        if warm is None:
            warm = _convert(model, sub, res.state, -1)
        search.append({"distance_mm": h, "cost": res.cost, "iterations": res.iterations,
                       "linearizations": res.linearizations, "observations": len(model.obs_point)})
        log.info("refine-colmap: start distance %g mm: cost %.6g after %d iterations with the window held",
                 h, res.cost, res.iterations)
        xyz = full_xyz.copy()
        xyz[keep] = res.state.xyz  # the subsample's points refined, the others at their start
        end = (res.cost, replace(res.state, xyz=xyz), res.iterations)
        if best is None or res.cost < best[0]:
            if best is not None:
                others.append(best)
            best = end
        else:
            others.append(end)
    if best is None:
        raise ValueError("no start distance to search")
    if len(keep) < len(full_xyz) and not np.all(np.isfinite(problem.residuals(best[1]))):
        # the subsample's poses put some of the other points (at their start) before the window: the
        # best distance again, on every point
        held_full = Solver(RefractiveProblem(full_model, interface, mount, estimate_distance, hold_window=True),
                           huber_px, bar=full_bar, baseline=baseline)
        h = search[[c["cost"] for c in search].index(best[0])]["distance_mm"]
        start = _convert(full_model, problem, full_virtual if declared else
                         _with_distance(full_model, full_virtual, mount, h), +1)
        res = held_full.run(start, SEARCH_ITERATIONS)
        search.append({"distance_mm": h, "cost": res.cost, "iterations": res.iterations,
                       "linearizations": res.linearizations, "observations": len(full_model.obs_point)})
        best = (res.cost, res.state, res.iterations)
    return search, best, sorted(others, key=lambda o: o[0])


def _paraxial_offset_mm(interface: Interface, normal_cam: np.ndarray, h: float) -> float:
    """n_m a: how far the paraxial virtual centre sits behind the real one along the normal."""
    ari = AriModel(PinholeModel(np.eye(3)), normal_cam, interface.thickness_mm, interface.index,
                   interface.medium_index, h)
    a = float(ari.apparent_points(np.zeros(3))[0] @ ari.normal_cam)
    return interface.medium_index * a


def _focal_rows(model: adapter.ColmapModel, c: int) -> np.ndarray:
    """Mask of camera c's COLMAP parameters that are focal lengths."""
    return np.asarray(model.param_map[c][:2].any(axis=0))


def _convert(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, direction: int) -> State:
    """Paraxial virtual cameras -> refractive start (direction +1), or back (-1): focal lengths
    divided (multiplied) by n_m, each frame's centre moved by +-n_m a along its window normal."""
    nm = problem.interface.medium_index
    params = []
    for c, p in enumerate(state.colmap_params):
        p = p.copy()
        p[_focal_rows(model, c)] *= nm ** (-direction)
        params.append(p)
    normals, dists = problem.image_windows(state)
    frames = list(state.rig_from_world)
    R, t = state.cam_from_world(model)
    for f in range(len(frames)):
        i = int(np.flatnonzero(model.image_frame == f)[0])
        n_world = R[i].T @ normals[i]
        shift = direction * _paraxial_offset_mm(problem.interface, normals[i], max(float(dists[i]), 1e-3))
        pose = frames[f]
        centre = -pose.R.T @ pose.t + shift * n_world
        frames[f] = Pose(pose.R, -pose.R @ centre)
    return replace(state, colmap_params=tuple(params), rig_from_world=tuple(frames))


def _initial_state(model: adapter.ColmapModel, mount: str, units: float) -> State:
    frames = tuple(Pose(p.R, p.t * units) for p in model.rig_from_world)
    sensors = tuple(Pose(p.R, p.t * units) for p in model.sensor_from_rig)
    C = len(model.camera_ids)
    state = State(tuple(p.copy() for p in model.colmap_params), frames, sensors, np.zeros((1, 3)), np.zeros(1),
                  model.xyz * units)
    if mount == "camera":
        return replace(state, normals=np.tile([0.0, 0.0, 1.0], (C, 1)), distances=np.zeros(C))
    R, _ = state.cam_from_world(model)
    axis = R[:, 2, :].mean(axis=0)  # optical axes in the world: rows z of cam_from_world
    return replace(state, normals=(axis / np.linalg.norm(axis))[None, :])


def _with_distance(model: adapter.ColmapModel, state: State, mount: str, h: float) -> State:
    """The window h in front of every camera (mount world: of the mean camera centre)."""
    if mount == "camera":
        return replace(state, distances=np.full(len(state.distances), h))
    R, t = state.cam_from_world(model)
    centres = -np.einsum("nji,nj->ni", R, t)
    return replace(state, distances=np.array([float(np.max(centres @ state.normals[0])) + h]))


def _restart_at(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, mount: str, h: float) -> State:
    """``state`` with its window moved to distance h, paraxially (the virtual cameras kept)."""
    return _convert(model, problem, _with_distance(model, _convert(model, problem, state, -1), mount, h), +1)


def _scaled(state: State, s: float, window: bool = True) -> State:
    """Every length times s (points, translations, window distances unless ``window`` is False: a
    declared plane stays where it was declared): the cost's near-flat direction."""
    return replace(state, xyz=state.xyz * s, rig_from_world=tuple(Pose(p.R, p.t * s) for p in state.rig_from_world),
                   sensor_from_rig=tuple(Pose(p.R, p.t * s) for p in state.sensor_from_rig),
                   distances=state.distances * s if window else state.distances)


PLANE_FRAMES = {"camera": "camera", "world": "world"}  # the only frame interface.plane may name, per mount


def _declared_start(model: adapter.ColmapModel, state: State, mount: str, plane: WindowPlane, path: Any) -> State:
    """The start with the window at the declared plane, checked: the normal points from the cameras into
    the scene and every camera is on the camera side of the face (one-line errors naming the field)."""
    where = "interface.plane"
    if plane.frame != PLANE_FRAMES[mount]:
        raise AriSfmError(path, f"{where}.frame: refine-colmap has no target frames: with mount {mount} the plane is "
                                f"in the {'COLMAP world (mm)' if mount == 'world' else 'camera (housing) frame'}; "
                                f"omit frame or write {PLANE_FRAMES[mount]!r} (got {plane.frame!r})")
    n, d = declared_window(plane)
    if mount == "camera":
        if n[2] <= 0:
            raise AriSfmError(path, f"{where}.normal must point from the camera into the scene (z > 0 in the camera "
                                    f"frame; got {n.round(4).tolist()})")
        if d <= 0:
            raise AriSfmError(path, f"{where}.point_mm: the camera-side face must be in front of the camera "
                                    f"(normal . point_mm > 0; got {d:.6g} mm)")
        return replace(state, normals=np.tile(n, (len(state.normals), 1)), distances=np.full(len(state.distances), d))
    R, t = state.cam_from_world(model)
    centres = -np.einsum("nji,nj->ni", R, t)
    if float(np.mean(R[:, 2, :] @ n)) <= 0:
        raise AriSfmError(path, f"{where}.normal must point from the cameras into the scene (got "
                                f"{n.round(4).tolist()}, against the cameras' mean viewing direction)")
    behind = int(np.sum(centres @ n >= d))
    if behind:
        raise AriSfmError(path, f"{where}.point_mm: {behind} of {len(centres)} camera centres are not on the camera "
                                f"side of the declared face (normal . X = {d:.6g} mm in the COLMAP world, in mm)")
    return replace(state, normals=n[None, :], distances=np.array([d]))


def _per_image_rms(model: adapter.ColmapModel, residuals: np.ndarray) -> dict[int, float]:
    e2 = np.sum(residuals ** 2, axis=1)
    sums = np.bincount(model.obs_image, e2, len(model.image_ids))
    counts = np.bincount(model.obs_image, minlength=len(model.image_ids))
    return {int(i): float(np.sqrt(sums[k] / counts[k])) for k, i in enumerate(model.image_ids) if counts[k]}


def _calibration(model: adapter.ColmapModel, problem: RefractiveProblem, state: State, mount: str,
                 cam_from_world: dict[int, Pose]) -> Calibration:
    """The refractive cameras as a Calibration (exact model); see :func:`refine_colmap`."""
    cams = {}
    names = [f"camera{int(cid)}" for cid in model.camera_ids]
    if mount == "camera":
        plane = float(np.max(state.distances))
        normal_world = np.array([0.0, 0.0, 1.0])
    else:
        plane = float(state.distances[0])
        normal_world = state.normals[0]
    for c, name in enumerate(names):
        p9 = model.params9(c, state.colmap_params[c])
        K = PinholeModel.from_params(p9).K
        if mount == "camera":
            n = state.normals[c]
            v = np.cross([0.0, 0.0, 1.0], n)
            sin = float(np.linalg.norm(v))
            R = np.eye(3) if sin < 1e-15 else rotation_from_rotvec(v / sin * np.arctan2(sin, n[2]))  # R e_z = n_c
            pose = Pose(R, -R @ np.array([0.0, 0.0, plane - state.distances[c]]))
        else:
            i = int(np.flatnonzero(model.image_camera == c)[0])
            pose = cam_from_world[int(model.image_ids[i])]
        cams[name] = CameraCalibration(name, model.image_sizes[c], K, p9[4:].copy(), pose)
    frame_note = ("each camera's housing frame: the port's near face is the plane z = distance_mm; "
                  "image poses: extra images_cam_from_world" if mount == "camera" else "the COLMAP model's world (mm)")
    frames = RefineColmapFrames(mount, frame_note, {n: int(cid) for n, cid in zip(names, model.camera_ids)},
                                {int(i): p for i, p in cam_from_world.items()})
    interface = replace(problem.interface, distance_mm=plane)
    return Calibration("exact", interface, normal_world, cams, {}, refine_colmap=frames)


def _state_reconstruction(rec: Any, model: adapter.ColmapModel, problem: RefractiveProblem, state: State) -> Any:
    sensors = {int(model.camera_ids[c]): state.sensor_from_rig[int(np.flatnonzero(model.image_camera == c)[0])]
               for c in range(len(model.camera_ids)) if problem.layout.sensors[c, 0] >= 0}
    return adapter.refined_reconstruction(rec, model, state.colmap_params, state.rig_from_world, sensors, state.xyz)


def refine_colmap(reconstruction: Any, interface: Interface, mount: str = "camera", model: str = "exact",
                  units_mm: float | None = None, scale_bar: tuple[int, int, float] | None = None,
                  baseline: tuple[str | int, str | int, float] | None = None, huber_px: float | None = HUBER_PX,
                  max_iterations: int = MAX_ITERATIONS, distances_mm: tuple[float, ...] | None = None,
                  approximation: str = "opencv",
                  backend: str = "numpy", progress: bool = False,
                  path: Any = "reconstruction", plane_path: Any = "interface.plane",
                  window_path: Any = "WINDOW.yaml") -> RefineResult:
    """Refine a COLMAP reconstruction made behind a flat window with the exact refractive model.

    ``reconstruction``: a pycolmap.Reconstruction or a model folder; ``interface``: the plate
    (thickness_mm, index, medium_index; distance_mm, if given, is the only distance candidate);
    ``mount``: ``camera`` (a housing per COLMAP camera) or ``world`` (one window fixed in the
    world); ``distances_mm``: distance candidates of the start search; ``approximation``: the COLMAP
    cameras written, ``opencv`` (pinhole + k1 k2 p1 p2, default: the distortion absorbs much of the
    port) or ``pinhole`` (the input's camera models); ``backend``: ``numpy`` (points Schur, this
    package's LM) or ``gtsam`` (one CustomFactor per image; slower; the start search stays numpy).
    ``interface.plane`` (optional, :mod:`.plane`): the declared window, frame ``camera`` (mount camera:
    each camera's housing frame) or ``world`` (mount world: the COLMAP world in mm); it replaces the
    start search; a sigma of 0 holds that part, > 0 makes it a prior. ``plane_path``: the file named
    in its errors; ``window_path``: the file named in errors about units and the scale bar. ``baseline``:
    ``(image, image, mm)``, two images (names, or COLMAP image ids) whose camera centres are ``mm`` apart:
    the scale, held by the solver as a scale bar is (numpy backend). See the module docstring for the
    start, the gauge and the scale.
    """
    t0 = time.perf_counter()
    _check_options(model, backend, approximation, mount, baseline is not None,
                   units_mm is not None or scale_bar is not None, path, window_path)
    if not isinstance(reconstruction, (str, Path)) and hasattr(reconstruction, "num_points3D"):
        rec = reconstruction
    else:
        path = Path(reconstruction)
        rec = read_model(path)
    cmodel = adapter.model_from_reconstruction(rec, path)
    _check_finite(cmodel, path)
    _check_redundancy(cmodel, path)
    base = None if baseline is None else _baseline(cmodel, baseline, path)
    units = _units_mm(cmodel, units_mm, scale_bar, window_path, base)
    bar = None
    if scale_bar is not None:
        where = {int(p): k for k, p in enumerate(cmodel.point3D_ids)}
        bar = ScaleBar(where[int(scale_bar[0])], where[int(scale_bar[1])], float(scale_bar[2]))
    plane = interface.plane
    estimate_distance = interface.medium_index != 1.0 and not (plane is not None and plane.sigma_mm == 0)
    hold_normal = plane is not None and plane.sigma_deg == 0
    problem = RefractiveProblem(cmodel, interface, mount, estimate_distance,
                                hold_window=hold_normal and not estimate_distance, hold_normal=hold_normal)
    solver = Solver(problem, huber_px, window_prior(plane, estimate_distance), bar, base)
    before = adapter.image_residuals_px(rec, cmodel)
    virtual = _initial_state(cmodel, mount, units)
    if plane is not None:  # the declared window is the start (held, or the prior's centre)
        virtual = _declared_start(cmodel, virtual, mount, plane, plane_path)
    candidates = _candidates_inside_scene(cmodel, virtual, interface,
                                          _distance_candidates(interface, virtual, estimate_distance, distances_mm),
                                          units_mm is not None or bar is not None or base is not None,
                                          plane is not None or interface.distance_mm is not None, window_path)
    blocks: list[dict] = []
    first = first_block(cmodel, virtual, mount)
    if first is not None:  # a long chain: the start slides outward from a middle block (the middle start distance)
        h = candidates[(len(candidates) - 1) // 2] if len(candidates) > 1 else candidates[0]
        whole = _convert(cmodel, problem, virtual if plane is not None else _with_distance(cmodel, virtual, mount, h),
                         +1)

        def block_solver(m: adapter.ColmapModel, held: np.ndarray | None) -> Solver:
            """The first block (``held`` None): the distance held, the normal free unless declared; a later
            one: its ``held`` frames, the window and the intrinsics held at the first block's (a block
            that fails cannot spoil what the others rely on)."""
            later = held is not None
            return Solver(RefractiveProblem(m, interface, mount, False, hold_window=later or plane is not None,
                                            held_frames=held, hold_intrinsics=later), huber_px)

        start, blocks = slid_start(cmodel, whole, first, block_solver)
        start, _ = _to_scale(start, bar, base, plane is None)
        search: list[dict] = []
        others = [(0.0, _restart_at(cmodel, problem, start, mount, c), 0) for c in candidates
                  if c != h and plane is None]
    else:
        search, best, others = _distance_search(cmodel, problem, interface, mount, estimate_distance, huber_px, bar,
                                                virtual, candidates, plane is not None, base)
        start = best[1]
    if not np.all(np.isfinite(problem.residuals(start))):
        raise AriSfmError(window_path, "no start puts every point beyond the window (the window is between a camera "
                                       "and points it sees at every candidate distance): check units_mm / scale_bar "
                                       "and the plate")
    pbar = None
    if progress:
        from tqdm import tqdm

        pbar = tqdm(total=max_iterations, desc="refine-colmap", unit="it", leave=False)

    def tick(it: int, cost: float) -> None:
        if pbar is not None:
            pbar.update(1)
            pbar.set_postfix(cost=f"{cost:.4g}")

    run = (lambda x: solver.run(x, max_iterations, tick)) if backend == "numpy" else (
        lambda x: solver.run_gtsam(x, max_iterations))
    pre = None
    if (bar is not None or base is not None) and FREE_SCALE_FIRST and not blocks:
        # the scale's valley first, without the bar (baseline), then the bar held
        free = Solver(problem, huber_px, window_prior(plane, estimate_distance))
        pre = free.run(start, max_iterations, tick) if backend == "numpy" else free.run_gtsam(start, max_iterations)
        start, factor = _to_scale(pre.state, bar, base, plane is None)
        log.info("refine-colmap: without the %s: cost %.6g in %d iterations; rescaled by %.6g to it",
                 "bar" if bar is not None else "baseline", pre.cost, pre.iterations, factor)
    result = run(start)
    iterations = (result.iterations + sum(c["iterations"] for c in search) + (pre.iterations if pre else 0)
                  + sum(b["iterations"] for b in blocks))
    linearizations = result.linearizations + (pre.linearizations
                                              if pre else 0) + sum(b["linearizations"] for b in blocks)
    restarts = []
    collapsed = estimate_distance and plane is None and _collapsed(result.state, problem, candidates)
    for _, other, _ in (others if collapsed else []):  # the distance ran toward 0: the other starts, lowest cost wins
        res = run(other)
        iterations += res.iterations
        linearizations += res.linearizations
        restarts.append({"distance_mm": problem.image_windows(res.state)[1].min().item(), "cost": res.cost})
        log.info("refine-colmap: the distance ran toward 0 from the best start; restart: cost %.6g (was %.6g)",
                 res.cost, result.cost)
        if res.cost < result.cost:
            result = res
    if pbar is not None:
        pbar.close()
    if not result.converged:
        log.warning("refine-colmap: not converged in %d iterations (max_iterations %d): the result and its sigmas "
                    "describe the last state, not an optimum; raise --max-iterations, or declare the port "
                    "(interface.plane) on surveys with short tracks", result.iterations, max_iterations)
    state = result.state
    residuals = problem.residuals(state)
    names = [f"camera{int(cid)}" for cid in cmodel.camera_ids]
    sigmas = uncertainty(solver, state, names, result.system)
    if collapsed and _collapsed(state, problem, candidates):  # still at ~0 after the restarts: say so, name it
        ran = (["distance_mm.world"] if mount == "world" else
               [f"distance_mm.{names[c]}"
                for c, d in enumerate(state.distances) if d < DISTANCE_COLLAPSE * min(candidates)])
        sigmas = replace(sigmas, weak=sigmas.weak + tuple(w for w in ran if w not in sigmas.weak))
        log.warning("refine-colmap: the port distance ran to %.3g mm from every start (%s mm): these images do not "
                    "determine it, and it follows the scale; declare a scale_bar or check units_mm, or declare the "
                    "port in WINDOW.yaml (interface.plane point_mm, sigma_mm for a prior)",
                    float(problem.image_windows(state)[1].min()), ", ".join(f"{c:g}" for c in candidates))
    R, t = state.cam_from_world(cmodel)
    cam_from_world = {int(i): Pose(R[k], t[k]) for k, i in enumerate(cmodel.image_ids)}
    refractive = _state_reconstruction(rec, cmodel, problem, state)
    virtual = _convert(cmodel, problem, state, -1)
    opencv = ({int(cid): _opencv_params(cmodel, c, virtual.colmap_params[c]) for c, cid in enumerate(cmodel.camera_ids)
               if cmodel.camera_models[c] != "FULL_OPENCV"} if approximation == "opencv" else None)
    approx = adapter.pinhole_approximation(_state_reconstruction(rec, cmodel, problem, virtual), opencv)
    approx_rms = adapter.image_residuals_px(approx, replace(cmodel, xyz=virtual.xyz))  # its points are the state's
    calibration = _calibration(cmodel, problem, state, mount, cam_from_world)
    e = np.linalg.norm(residuals, axis=1)
    ids = [f"camera{int(cid)}" for cid in cmodel.camera_ids]
    window = (WindowEstimate(normal_cam={n: state.normals[c].copy() for c, n in enumerate(ids)},
                             distance_mm={n: float(state.distances[c]) for c, n in enumerate(ids)})
              if mount == "camera" else WindowEstimate(normal_world=state.normals[0].copy(),
                                                       plane_mm=float(state.distances[0])))
    report = RefineReport(
        mount=mount, model=model, backend=backend, units_mm=units,
        interface=Plate(interface.thickness_mm, interface.index, interface.medium_index),
        counts=RefineCounts(len(cmodel.camera_ids), len(cmodel.frame_ids), len(cmodel.image_ids),
                            len(cmodel.point3D_ids), len(cmodel.obs_image), problem.layout.size),
        estimated="intrinsics per camera, rig_from_world per frame (the first held: gauge), sensor_from_rig per "
                  "non-reference sensor, window " + _window_parts(hold_normal, estimate_distance, plane is not None)
                  + " per " + ("camera (housing)" if mount == "camera" else "world") + ", 3D points",
        scale=("held by the scale bar (a term of the solver)" if bar is not None else
               "held by the baseline between two images' camera centres (a term of the solver)" if base is not None
               else "the input's units times units_mm, refined by refraction (weakly observable through the plate)"),
        distance_search=tuple(search), restarts=tuple(restarts),
        iterations=iterations, converged=result.converged,
        linearizations=linearizations, search_linearizations=sum(c["linearizations"] for c in search),
        uncertainty=sigmas, cost_start=float(result.initial_cost), cost_final=float(result.cost),
        time_s=time.perf_counter() - t0,
        before=Reprojection("COLMAP pinhole", _rms(before), before),
        after=Reprojection("exact", float(np.sqrt(np.mean(e ** 2))), _per_image_rms(cmodel, residuals),
                           mean_px=float(np.mean(e))),
        pinhole_approximation=Reprojection(approximation.upper() if approximation == "opencv" else "input's",
                                           _rms(approx_rms), approx_rms, model_key="camera_model"),
        window=window,
        plane=None if plane is None else DeclaredPlaneReport(
            plane.frame, declared_window(plane)[0], np.asarray(plane.point_mm, float),
            "held" if hold_normal else f"prior {plane.sigma_deg:g} deg",
            f"prior {plane.sigma_mm:g} mm" if estimate_distance else "held"),
        scale_bar=None if bar is None or scale_bar is None else ScaleBarReport(
            (int(scale_bar[0]), int(scale_bar[1])), bar.length_mm, bar.sigma_mm, bar.length(state.xyz)),
        baseline=None if base is None else BaselineReport(
            (cmodel.image_names[base.a], cmodel.image_names[base.b]), base.length_mm, base.sigma_mm,
            base.length(state)))
    bar_report, base_report = report.scale_bar, report.baseline
    if bar is not None and bar_report is not None and abs(bar_report.refined_mm / bar.length_mm - 1.0) > 1e-3:
        log.warning("refine-colmap: the scale bar is %.6g mm after the refinement (declared %.6g mm): the images "
                    "pull against it", bar_report.refined_mm, bar.length_mm)
    if base is not None and base_report is not None and abs(base_report.refined_mm / base.length_mm - 1.0) > 1e-3:
        raise AriSfmError(path, f"baseline: the refinement ends with images {base_report.images[0]} and "
                                f"{base_report.images[1]} {base_report.refined_mm:.6g} mm apart, not the "
                                f"{base.length_mm:.6g} mm given: the images pull against it (check the names and "
                                "the distance)")
    log.warning("refine-colmap: the COLMAP cameras written are the best %s approximation of the refractive "
                "cameras (poses are virtual; real poses in calibration.json): %.3f px RMS (the exact model: %.3f px)",
                approximation, report.pinhole_approximation.rms_px, report.after.rms_px)
    return RefineResult(approx, refractive, calibration, state, report)


def _check_options(model: str, backend: str, approximation: str, mount: str, baseline: bool, other_scale: bool,
                   path: Any, window_path: Any) -> None:
    """refine_colmap's choices, each checked (``baseline``: one is given; ``other_scale``: units_mm or a
    scale bar is)."""
    if model != "exact":
        raise AriSfmError(path, f"refine-colmap: model {model!r} is not supported (exact)")
    if backend not in ("numpy", "gtsam"):
        raise AriSfmError(path, f"backend must be numpy or gtsam (got {backend!r})")
    if approximation not in ("opencv", "pinhole"):
        raise AriSfmError(path, f"approximation must be opencv or pinhole (got {approximation!r})")
    if mount not in MOUNTS:
        raise AriSfmError(path, f"mount must be one of {', '.join(MOUNTS)} (got {mount!r})")
    if baseline and other_scale:
        raise AriSfmError(window_path, "gives units_mm or scale_bar and a baseline gives the scale too: give it once")
    if baseline and backend != "numpy":
        raise AriSfmError(path, "baseline: a term of the numpy backend only (backend numpy, or a scale_bar)")


def _distance_candidates(interface: Interface, virtual: Any, estimate_distance: bool,
                         distances_mm: tuple[float, ...] | None) -> tuple[float, ...]:
    """The start distances to try: the declared window's (``virtual``, its start), the interface's
    distance_mm, the air's placeholder when the distance is not estimated, else ``distances_mm`` or the
    default candidates."""
    if interface.plane is not None:
        return (float(virtual.distances[0]),)
    if interface.distance_mm is not None:
        return (float(interface.distance_mm),)
    if not estimate_distance:
        return (AIR_DISTANCE_MM,)
    return tuple(distances_mm or DISTANCE_CANDIDATES_MM)


def _window_parts(hold_normal: bool, estimate_distance: bool, declared: bool) -> str:
    """What of the window is estimated, for the report."""
    parts = [p for p, free in (("normal", not hold_normal), ("distance", estimate_distance)) if free]
    why = "held at the declared plane" if declared else "distance held: unobservable in air"
    if not parts:
        return f"(none: {why})"
    return " and ".join(parts) + ("" if len(parts) == 2 else f" ({why})") + (" with the declared plane's prior"
                                                                               if declared else "")


def _opencv_params(model: adapter.ColmapModel, c: int, colmap_params: np.ndarray) -> np.ndarray:
    """Camera c's parameters as COLMAP OPENCV [fx fy cx cy k1 k2 p1 p2] (COLMAP pixels)."""
    p9 = model.params9(c, colmap_params)
    return np.r_[p9[:2], p9[2:4] + adapter.COLMAP_PIXEL_OFFSET, p9[4:8]]


def _rms(per_image: dict[int, float]) -> float:
    v = np.array(list(per_image.values()))
    return float(np.sqrt(np.mean(v ** 2))) if len(v) else float("nan")


def write_refined(result: RefineResult, out_dir: str | Path) -> Path:
    """OUT: the COLMAP model (the cameras' best COLMAP approximation, refined points), calibration.json,
    refine.json. Everything is written into a temporary folder inside OUT first, then renamed into
    place file by file (refine.json last): a failed write (a full disk, a signal) leaves OUT's
    previous files as they were and no partial file."""
    import shutil
    import tempfile

    from ari_sfm.io import write_json_atomic

    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=".refine-colmap.", dir=out))
    except OSError as exc:
        raise AriSfmError(out, f"cannot write: {exc.strerror or exc}") from None
    try:
        _write_model(result.reconstruction, tmp)
        save_calibration(result.calibration, tmp / "calibration.json")
        write_json_atomic(tmp / "refine.json", result.report.to_json())
        names = sorted(p.name for p in tmp.iterdir() if p.name != "refine.json") + ["refine.json"]
        for name in names:
            os.replace(tmp / name, out / name)
    except (OSError, RuntimeError) as exc:  # pycolmap's writer raises RuntimeError
        raise AriSfmError(out, f"cannot write: {getattr(exc, 'strerror', None) or exc}") from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    return out


def _write_model(reconstruction: Any, folder: Path) -> None:
    """The COLMAP model's binary files in ``folder`` (pycolmap's writer)."""
    reconstruction.write(str(folder))
