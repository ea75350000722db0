"""The 3D error of a reconstruction against a reference geometry (a mesh or a point cloud), with Open3D.

``reference_errors(points, path)``:

1. reads the reference (``o3d.io.read_triangle_mesh``; a file without
   triangles is read as a point cloud), in its own coordinates (a CAD model,
   a scan, the target as built);
2. registers the reconstructed points onto it (rigid, no scale): from the
   identity and the principal-axes alignments of the two point sets, Open3D's
   point-to-point ICP (``registration_icp``, coarse correspondence distances)
   against a dense sample of the mesh (or the cloud); the start whose result
   lies closest to the surface goes on through the fine ICP stages and
   Gauss-Newton point-to-plane steps on the surface itself (the mesh's
   closest points and face normals from ``RaycastingScene``; the cloud's
   nearest points and estimated normals);
3. measures every point's distance to the surface: for a mesh, Open3D's
   ``RaycastingScene.compute_distance`` (exact point-to-triangle distance);
   for a cloud, the distance to the nearest reference point (which includes
   the cloud's sampling: use a mesh where one exists).

Returned: a :class:`ReferenceErrors` (lengths in mm); its ``to_json()`` is metrics.json's
``reference``: ``{"path", "kind": "mesh" | "cloud", "count", "registration": {"reference_from_world": 4x4,
"rotation_deg", "translation_mm", "fitness", "inlier_rmse_mm"}, "distance_mm": {"mean", "rms", "max",
"p95"}, "frames": {name: {"rms", "max"}}}``.

Limits: what the reference's shape does not fix, registration cannot
recover. For faces that are all parallel (a board moved along a stage), the
slide within the plane and the turn about its normal are set by the faces'
edges only; the distances do not depend on them while the points stay inside
the faces. The registration absorbs any rigid error of the reconstruction
(as ``truth`` in metrics.json does after alignment): what remains is its shape error.
"""
from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..deps import require_open3d
from ..errors import AriSfmError
from .points import Points

log = logging.getLogger(__name__)

ICP_SCHEDULE = (0.2, 0.05, 0.01, 0.002)  # correspondence distances, fractions of the points' bounding-box diagonal
ICP_ITERATIONS = 100  # per stage
SAMPLES_PER_POINT = 20  # mesh samples for ICP per reconstructed point (at least MIN_SAMPLES)
MIN_SAMPLES = 50_000
SEED = 0  # Open3D's sampling is seeded: the same inputs give the same figures


@dataclass(frozen=True)
class Registration:
    """The rigid motion that puts the reconstruction on the reference, and ICP's figures."""

    reference_from_world: np.ndarray  # (4, 4), mm
    rotation_deg: float
    translation_mm: float
    fitness: float  # ICP's fraction of points with a correspondence
    inlier_rmse_mm: float

    def to_json(self) -> dict[str, Any]:
        return {"reference_from_world": np.asarray(self.reference_from_world, float).tolist(),
                "rotation_deg": self.rotation_deg, "translation_mm": self.translation_mm,
                "fitness": self.fitness, "inlier_rmse_mm": self.inlier_rmse_mm}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> Registration:
        return cls(np.asarray(d["reference_from_world"], float), float(d["rotation_deg"]),
                   float(d["translation_mm"]), float(d["fitness"]), float(d["inlier_rmse_mm"]))


@dataclass(frozen=True)
class SurfaceDistances:
    """Point-to-surface distances after registration (mm)."""

    mean: float
    rms: float
    max: float
    p95: float

    def to_json(self) -> dict[str, float]:
        return {"mean": self.mean, "rms": self.rms, "max": self.max, "p95": self.p95}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> SurfaceDistances:
        return cls(float(d["mean"]), float(d["rms"]), float(d["max"]), float(d["p95"]))


@dataclass(frozen=True)
class FrameDistances:
    """One frame's point-to-surface distances (mm)."""

    rms: float
    max: float

    def to_json(self) -> dict[str, float]:
        return {"rms": self.rms, "max": self.max}


@dataclass(frozen=True)
class ReferenceErrors:
    """What :func:`reference_errors` measures: metrics.json's ``reference`` (``to_json``/``from_json``)."""

    path: str  # the reference file, absolute
    kind: str  # "mesh" or "cloud"
    count: int  # reconstructed points registered
    registration: Registration
    distance_mm: SurfaceDistances
    frames: Mapping[str, FrameDistances] = field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        return {"path": self.path, "kind": self.kind, "count": self.count,
                "registration": self.registration.to_json(), "distance_mm": self.distance_mm.to_json(),
                "frames": {n: f.to_json() for n, f in self.frames.items()}}

    @classmethod
    def from_json(cls, d: Mapping[str, Any]) -> ReferenceErrors:
        return cls(str(d["path"]), str(d["kind"]), int(d["count"]), Registration.from_json(d["registration"]),
                   SurfaceDistances.from_json(d["distance_mm"]),
                   {n: FrameDistances(float(f["rms"]), float(f["max"])) for n, f in d["frames"].items()})


MAX_COORDINATE_MM = 1e7  # a reference coordinate beyond 10 km is not in mm (or not a coordinate)
MIN_FITNESS = 0.5  # registered: at least half the points within REGISTERED_FRACTION of the points' extent
REGISTERED_FRACTION = 0.05  # of the bounding-box diagonal (ICP_SCHEDULE's second stage)
PLY_TYPES = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2, "uint16": 2,
             "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4, "double": 8, "float64": 8}


def check_ply(path: Path) -> None:
    """Check that a .ply file is as long as its header declares (not a truncated copy or download).

    Found here rather than by RPly, which prints its own error line and returns part of the geometry.

    Args:
        path: the .ply file.

    Raises:
        AriSfmError: if the file is not a PLY file or is truncated.
    """
    with open(path, "rb") as f:
        head = f.read(65536)
    end = head.find(b"end_header")
    if not head.startswith(b"ply") or end < 0:
        raise AriSfmError(path, "not a PLY file (no 'ply' ... 'end_header' header)")
    body_start = head.index(b"\n", end) + 1 if b"\n" in head[end:] else len(head)
    lines = head[:end].decode("ascii", errors="replace").splitlines()
    fmt: str | None = None
    elements: list[tuple[str, int]] = []  # (name, count)
    nbytes: list[int] = []  # each element's fixed bytes and minimum list bytes
    for line in lines:
        words = line.split()
        if words[:1] == ["format"] and len(words) > 1:
            fmt = words[1]
        elif words[:1] == ["element"] and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2])))
            nbytes.append(0)
        elif words[:1] == ["property"] and elements and len(words) >= 3:
            if words[1] == "list" and len(words) >= 5:
                items = 3 if words[4] in ("vertex_indices", "vertex_index") else 0  # a face has >= 3 corners
                nbytes[-1] += PLY_TYPES.get(words[2], 1) + items * PLY_TYPES.get(words[3], 4)
            else:
                nbytes[-1] += PLY_TYPES.get(words[1], 4)
    size = path.stat().st_size
    if fmt in ("binary_little_endian", "binary_big_endian"):
        needed = body_start + sum(count * size_of for (_, count), size_of in zip(elements, nbytes))
        if size < needed:
            raise AriSfmError(path, f"truncated: its header declares {', '.join(f'{c} {n}' for n, c in elements)} "
                                    f"({needed} bytes at least), the file has {size} bytes")
    elif fmt == "ascii":
        with open(path, "rb") as f:
            f.seek(body_start)
            rows = sum(1 for line in f if line.strip())
        declared = sum(count for _, count in elements)
        if rows < declared:
            raise AriSfmError(path, f"truncated: its header declares {declared} rows "
                                    f"({', '.join(f'{c} {n}' for n, c in elements)}), the file has {rows}")


def load_reference(path: str | Path) -> tuple[Any, str]:
    """Read the reference geometry: a mesh, or a point cloud when the file has no triangles.

    Args:
        path: the mesh or point-cloud file (.ply, .obj, .stl, .off, .gltf; .ply, .pcd, .xyz), in mm.

    Returns:
        The geometry as an Open3D legacy TriangleMesh or PointCloud, and its kind ('mesh' / 'cloud').

    Raises:
        AriSfmError: one line, for a missing, empty or truncated file; non-finite coordinates or coordinates
            beyond MAX_COORDINATE_MM; points that are all one point or on one line (nothing to register onto).
    """
    o3d = require_open3d()
    path = Path(path)
    if not path.is_file():
        raise AriSfmError(path, "reference geometry not found" if not path.exists() else "is not a file")
    if path.suffix.lower() == ".ply":
        check_ply(path)
    verbosity = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)  # Open3D warns on stdout for unknown formats
    try:
        mesh = o3d.io.read_triangle_mesh(str(path))
        if len(mesh.triangles):
            vertices = np.asarray(mesh.vertices)
            geometry, kind = mesh, "mesh"
        else:
            cloud = o3d.io.read_point_cloud(str(path))
            vertices = np.asarray(cloud.points)
            geometry, kind = cloud, "cloud"
    finally:
        o3d.utility.set_verbosity_level(verbosity)
    if len(vertices) == 0:
        raise AriSfmError(path, "no triangles or points read (a .ply, .obj, .stl, .off or .gltf mesh, or a point "
                                "cloud .ply, .pcd, .xyz)")
    if not np.isfinite(vertices).all():
        raise AriSfmError(path, "reference holds non-finite coordinates")
    if kind == "cloud" and len(vertices) < 3:
        raise AriSfmError(path, f"a reference cloud needs at least 3 points (got {len(vertices)})")
    largest = float(np.abs(vertices).max())
    if largest > MAX_COORDINATE_MM:
        raise AriSfmError(path, f"coordinates up to {largest:.3g}: out of range (lengths in mm, at most "
                                f"{MAX_COORDINATE_MM:g})")
    spread = np.linalg.svd(vertices - vertices.mean(axis=0), compute_uv=False)
    if spread[0] <= 1e-9 * max(largest, 1.0):
        raise AriSfmError(path, f"degenerate: all its {len(vertices)} points are one point")
    if len(spread) < 2 or spread[1] <= 1e-9 * spread[0]:
        raise AriSfmError(path, f"degenerate: all its {len(vertices)} points lie on one line (registration "
                                "needs a surface)")
    return geometry, kind


def _principal_starts(source: np.ndarray, target: np.ndarray) -> list[np.ndarray]:
    """4x4 starts mapping source onto target: identity, centroid shift, and the 4 proper principal-axes matches."""
    cs, ct = source.mean(axis=0), target.mean(axis=0)
    starts = [np.eye(4)]
    shift = np.eye(4)
    shift[:3, 3] = ct - cs
    starts.append(shift)
    _, _, Vs = np.linalg.svd(source - cs, full_matrices=False)
    _, _, Vt = np.linalg.svd(target - ct, full_matrices=False)
    for signs in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        D = np.diag([signs[0], signs[1], 1.0])
        R = Vt.T @ D @ Vs
        if np.linalg.det(R) < 0:
            R = Vt.T @ np.diag([signs[0], signs[1], -1.0]) @ Vs
        T = np.eye(4)
        T[:3, :3], T[:3, 3] = R, ct - R @ cs
        starts.append(T)
    return starts


def _refine_point_to_plane(closest: Any, xyz: np.ndarray, T: np.ndarray, max_distance: float,
                           iterations: int = 20) -> np.ndarray:
    """Gauss-Newton point-to-plane steps after the point-to-point ICP: ``closest(X)`` gives each point's
    closest surface point and normal (a mesh: RaycastingScene's closest point and face normal, exact; a
    cloud: its nearest point and estimated normal). Minimum-norm steps leave alone the motions the
    surface does not fix (slides along parallel faces)."""
    from ..geometry import rotation_from_rotvec

    R, t = T[:3, :3].copy(), T[:3, 3].copy()
    for _ in range(iterations):
        X = xyz @ R.T + t
        foot, n = closest(X)
        r = np.sum((X - foot) * n, axis=1)
        use = np.abs(r) < max_distance
        if use.sum() < 6:
            break
        J = np.hstack([np.cross(X[use], n[use]), n[use]])
        step = np.linalg.lstsq(J, -r[use], rcond=1e-6)[0]  # min-norm where the faces leave a motion free
        dR = rotation_from_rotvec(step[:3])
        R, t = dR @ R, dR @ t + step[3:]
        if np.linalg.norm(step) < 1e-10:
            break
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = R, t
    return out


def reference_errors(points: Points, path: str | Path) -> ReferenceErrors:
    """Register the reconstruction onto a reference geometry and measure point-to-surface distances.

    Args:
        points: the reconstructed points.
        path: the reference's mesh or point-cloud file (see :func:`load_reference`).

    Returns:
        The registration and the distances (module docstring).

    Raises:
        AriSfmError: for a bad reference, fewer than 3 points, or a failed registration.
    """
    o3d = require_open3d()
    geometry, kind = load_reference(path)
    names = [n for n, f in points.frames.items() if len(f)]
    xyz = np.concatenate([points.frames[n].xyz for n in names]) if names else np.zeros((0, 3))
    if len(xyz) < 3:
        raise AriSfmError(path, f"registration needs at least 3 reconstructed points (got {len(xyz)})")
    diag = float(np.linalg.norm(np.ptp(xyz, axis=0))) or 1.0
    # work around the reference's centroid: float32 distance queries keep ~1e-5 mm there
    ref_xyz = np.asarray(geometry.vertices if kind == "mesh" else geometry.points)
    origin = ref_xyz.mean(axis=0)
    geometry = geometry.translate(-origin)  # legacy translate acts in place: the loaded copy only
    if kind == "mesh":
        geometry.compute_triangle_normals()
        geometry.compute_vertex_normals()
        o3d.utility.random.seed(SEED)
        target = geometry.sample_points_uniformly(number_of_points=max(MIN_SAMPLES, SAMPLES_PER_POINT * len(xyz)),
                                                  use_triangle_normal=True)
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(geometry))

        def distances(p: np.ndarray) -> np.ndarray:
            return scene.compute_distance(o3d.core.Tensor(p.astype(np.float32))).numpy().astype(float)

        def closest(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            found = scene.compute_closest_points(o3d.core.Tensor(X.astype(np.float32)))
            return found["points"].numpy().astype(float), found["primitive_normals"].numpy().astype(float)
    else:
        target = geometry
        diag_ref = float(np.linalg.norm(np.ptp(np.asarray(target.points), axis=0)))
        if not target.has_normals():
            target.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius=0.02 * diag_ref, max_nn=30))

        def distances(p: np.ndarray) -> np.ndarray:
            query = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(p))
            return np.asarray(query.compute_point_cloud_distance(target), dtype=float)

        nns = o3d.core.nns.NearestNeighborSearch(o3d.core.Tensor(np.asarray(target.points)))
        nns.knn_index()
        cloud_xyz, cloud_normals = np.asarray(target.points), np.asarray(target.normals)

        def closest(X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            index = nns.knn_search(o3d.core.Tensor(X), 1)[0].numpy().reshape(-1)
            return cloud_xyz[index], cloud_normals[index]
    source = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(xyz))
    # point to point: well posed even where the faces are parallel (point-to-plane ICP slides along them)
    method = o3d.pipelines.registration.TransformationEstimationPointToPoint()
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(relative_fitness=1e-9, relative_rmse=1e-9,
                                                                 max_iteration=ICP_ITERATIONS)


    def icp(T: np.ndarray, fractions: tuple[float, ...]) -> tuple[np.ndarray, Any]:
        result = None
        for fraction in fractions:
            result = o3d.pipelines.registration.registration_icp(source, target, fraction * diag, T, method, criteria)
            T = np.asarray(result.transformation)
        return T, result

    def rms_distance(T: np.ndarray) -> float:
        return float(np.sqrt(np.mean(distances(xyz @ T[:3, :3].T + T[:3, 3]) ** 2)))

    # every start through the coarse stages; the one closest to the surface through the fine ones
    coarse = [icp(start, ICP_SCHEDULE[:2])[0] for start in _principal_starts(xyz, np.asarray(target.points))]
    T, result = icp(min(coarse, key=rms_distance), ICP_SCHEDULE[2:])
    T = _refine_point_to_plane(closest, xyz, T, ICP_SCHEDULE[-1] * diag)
    d = distances(xyz @ T[:3, :3].T + T[:3, 3])
    registered = float(np.mean(d <= REGISTERED_FRACTION * diag))
    if not registered >= MIN_FITNESS:  # the figures would measure a failed registration (distances ~1e30 mm)
        raise AriSfmError(path, f"registration failed: {registered:.0%} of the {len(xyz)} reconstructed points lie "
                                f"within {REGISTERED_FRACTION * diag:.3g} mm of the reference after ICP (at least "
                                f"{MIN_FITNESS:.0%} needed): is it this scene's geometry, in mm, covering the points?")
    world_to_ref = np.eye(4)
    world_to_ref[:3, :3] = T[:3, :3]
    world_to_ref[:3, 3] = T[:3, 3] + origin  # undo the working shift
    angle = float(np.degrees(np.arccos(np.clip((np.trace(T[:3, :3]) - 1.0) / 2.0, -1.0, 1.0))))
    frames: dict[str, FrameDistances] = {}
    start = 0
    for n in names:
        k = len(points.frames[n])
        fd = d[start:start + k]
        start += k
        frames[n] = FrameDistances(float(np.sqrt(np.mean(fd**2))), float(fd.max()))
    log.info("reference %s: %d points registered (fitness %.3f), distance rms %.4f mm", path, len(xyz),
             result.fitness, float(np.sqrt(np.mean(d**2))))
    return ReferenceErrors(
        str(Path(path).resolve()), kind, int(len(xyz)),
        Registration(world_to_ref, angle, float(np.linalg.norm(world_to_ref[:3, 3])), float(result.fitness),
                     float(result.inlier_rmse)),
        SurfaceDistances(float(d.mean()), float(np.sqrt(np.mean(d**2))), float(d.max()), float(np.percentile(d, 95))),
        frames)
