"""Self-calibration's bundle adjustment: the particles as landmarks, every camera free, the window held.

The window's plane is held in the lab (the calibration's world frame) and every camera's pose is
estimated, camera 0 included. The particles do not see the motions that keep the window's plane
(:func:`window_gauge`: for one window under water a rotation about its normal and a translation within
its plane; in air also the translation along the normal, whose distance refraction does not show): those
are held as the *gauge*, by stiff rows saying that the rig's mean motion from the start along them is
zero (:class:`Gauge`). The scale, which the particles barely determine (PHYSICS.md), is held by one more
stiff row: the sum of the distances between every pair of camera centres at the start's value.

The intrinsics (fx fy cx cy, and k1 when the start estimated distortion) are estimated with the
start calibration's values and sigmas (its ``uncertainty``) as priors. Prior rows are whitened against
the particles' pixel noise (``noise_px``), so that the two kinds of information are weighed right.

The problem is refine-colmap's refractive problem (:class:`ari_sfm.colmap.refine.problem.RefractiveProblem`,
world mount, ``camera_windows`` for several windows): one rig frame (camera 0's pose, a variable
here) and each other camera's sensor_from_rig. The points are eliminated by the Schur complement
(:mod:`ari_sfm.solver.schur`), the project's Levenberg-Marquardt solves it; GTSAM solves the
same graph (``backend='gtsam'``). Perturbations are the problem's: ``(R, t) -> (exp(w) R, t + v)``.
"""
from __future__ import annotations

import logging
import math
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, cast

import numpy as np

from ..calibration.record import Calibration
from ..errors import AriSfmError
from ..geometry import Pose, rotation_angle_deg
from ..models import PinholeModel
from ..models.pinhole import PARAM_NAMES
from ..solver.bundle import Rows, RowTerm
from .disparity import ParticleSet
from .selfcal_report import Adjustment, CameraSigma

if TYPE_CHECKING:
    from ..colmap.refine.gtsam_graph import GtsamRefinement
    from ..colmap.refine.problem import Layout, RefractiveProblem, State
    from ..colmap.refine.solver import Solver

log = logging.getLogger(__name__)

STIFF_SIGMA_MM = 0.01  # the gauge and scale rows' sigma (mm of mean camera motion / of the baseline sum): stiff against
# the particles (they leave ~1 mm on the scale), not so stiff that their curvature (the log, the distances) stalls LM
RIG_TILT_PRIOR_DEG = 0.5  # the rig's mean tilt to the window(s) (and its distance, as the same motion at the
# particles) held at the start's by a prior this wide: refraction determines it weakly, and unheld the
# adjustment's steps wander along it (measured: 0.5 deg steps, then 50 iterations crawling back)
INTRINSICS_FREE = ("fx", "fy", "cx", "cy")  # estimated with the start's priors (k1 too when it has distortion)
UNKNOWN_PRIOR_PX = 5.0  # a start whose uncertainty lacks a camera's parameter (or guessed it): its prior this wide (px)
HELD_SIGMA_PX = 1e-3  # a start's sigma below this was held, not measured (calibrate holds by a 1e-4 px prior)
UNKNOWN_PRIOR_K1 = 0.01
GTSAM_MAX_LANDMARKS = 400  # --backend gtsam beyond this: refused (its time grows as the cube: 300 5.6 s, 400 14 s)
CHI2_STOP = 0.01  # Levenberg-Marquardt stops when a step lowers chi^2 by less than this
LAMBDA_INITIAL = 1e-8  # Levenberg-Marquardt's first lambda: the particles' problem is near Gauss-Newton's (from
# 1e-4, measured: 20-50 iterations crawling down a valley, against 5)
NOISE_REFIT = 0.2  # the prior rows are re-weighted (one more solve) when the fitted noise differs by more
INTRINSICS_MODES = ("prior", "held", "free")
BACKENDS = ("numpy", "gtsam")


def _skew(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _log_rotation(R: np.ndarray) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    return Rotation.from_matrix(R).as_rotvec()


# --------------------------------------------------------------------------- the model


def free_intrinsics(calibration: Calibration, mode: str) -> tuple[int, ...]:
    """The intrinsic parameters self-calibration estimates.

    No parameter when held, or in mode "prior" without the start's uncertainty to weigh them (a warning is
    logged); else fx fy cx cy, and k1 when the start has lens distortion.

    Args:
        calibration: The start calibration.
        mode: One of :data:`INTRINSICS_MODES` ("prior", "held", "free").

    Returns:
        Indices into [fx fy cx cy k1 k2 p1 p2 k3].
    """
    if mode == "held" or (mode == "prior" and calibration.uncertainty is None):
        if mode == "prior":
            log.warning("self-calibration: the start calibration has no uncertainty to weigh its intrinsics "
                        "against the particles: they are held (--intrinsics free estimates them without priors)")
        return ()
    has_distortion = any(np.any(np.asarray(c.dist, float) != 0.0) for c in calibration.cameras.values())
    names = INTRINSICS_FREE + (("k1",) if has_distortion else ())
    return tuple(PARAM_NAMES.index(n) for n in names)


def landmark_model(calibration: Calibration, particles: ParticleSet, free: Sequence[int]):
    """The particles as a one-frame COLMAP-like model: one image per camera, camera 0 the rig's reference sensor.

    Args:
        calibration: The start calibration (the cameras' parameters and poses).
        particles: The matched particles: each one a point, each of its used images an observation.
        free: The indices (of the 9 intrinsics) that are variables.

    Returns:
        The :class:`~ari_sfm.colmap.adapter.ColmapModel`.
    """
    from ..colmap.adapter import ColmapModel

    names = list(calibration.cameras)
    C = len(names)
    cam0 = calibration.cameras[names[0]].cam_from_world
    params, maps, offsets = [], [], []
    for n in names:
        p9 = np.asarray(calibration.cameras[n].params, float)
        M = np.zeros((9, len(free)))
        for j, i in enumerate(free):
            M[i, j] = 1.0
        off = p9.copy()
        off[list(free)] = 0.0
        params.append(p9[list(free)].copy())
        maps.append(M)
        offsets.append(off)
    obs_point, obs_image = np.nonzero(particles.used)
    return ColmapModel(
        camera_ids=np.arange(C), camera_models=("OPENCV",) * C,
        image_sizes=tuple(cast("tuple[int, int]", tuple(calibration.cameras[n].image_size)) for n in names),
        colmap_params=tuple(params), param_map=tuple(maps), param_offset=tuple(offsets),
        frame_ids=np.zeros(1, int), rig_from_world=(cam0,), image_ids=np.arange(C), image_names=tuple(names),
        image_camera=np.arange(C), image_frame=np.zeros(C, int),
        sensor_from_rig=tuple(calibration.cameras[n].cam_from_world.compose(cam0.inverse()) for n in names),
        point3D_ids=np.arange(len(particles.xyz)), xyz=particles.xyz.copy(),
        obs_image=obs_image, obs_point=obs_point, obs_uv=particles.pixels[obs_point, obs_image],
        image_is_ref=np.arange(C) == 0)


def window_planes(calibration: Calibration) -> tuple[np.ndarray, np.ndarray]:
    """Every window's normal (W, 3) and near face offset (W,) in the world (``normal . X = plane`` on the face)."""
    windows = calibration.window_list()
    return (np.array([np.asarray(w.normal_world, float) for w in windows]),
            np.array([w.plane_mm(calibration) for w in windows], dtype=float))


def window_gauge(normals: np.ndarray, in_air: Sequence[bool], complement: bool = False) -> np.ndarray:
    """The rigid motions that keep every window's plane, as orthonormal twists.

    A twist is [omega, v] (rotation about the world origin, translation): omega along each normal n, v within
    its plane (in air also along n: the distance is not observed). One window under water: K = 3; two
    non-parallel: K = 1.

    Args:
        normals: Each window's unit normal in the world (W, 3).
        in_air: Whether air is behind each window (W,).
        complement: Return the orthonormal complement instead: the rigid motions that move a window's plane.

    Returns:
        The twists (K, 6) (with ``complement``: (6 - K, 6)).
    """
    rows = []
    for n, air in zip(np.asarray(normals, float), in_air):
        basis = np.linalg.svd(n[None, :])[2][1:]  # two unit vectors perpendicular to n
        rows += [np.concatenate([b, np.zeros(3)]) for b in basis]  # omega has no part across n
        if not air:
            rows.append(np.concatenate([np.zeros(3), n]))  # v has no part along n
    A = np.array(rows)
    _, s, Vt = np.linalg.svd(A)
    rank = int(np.sum(s > 1e-9 * s.max()))
    return Vt[:rank] if complement else Vt[rank:]


# --------------------------------------------------------------------------- camera motions


def camera_poses(state) -> tuple[np.ndarray, np.ndarray]:
    """(C, 3, 3) rotations and (C, 3) translations of every camera's cam_from_world (one image per camera)."""
    f = state.rig_from_world[0]
    R = np.array([s.R @ f.R for s in state.sensor_from_rig])
    t = np.array([s.R @ f.t + s.t for s in state.sensor_from_rig])
    return R, t


def motion_jacobians(state, layout) -> tuple[np.ndarray, np.ndarray]:
    """Jacobians of each camera's world rotation increment and centre with respect to the reduced variables.

    The rotation increment rho_c: world_from_cam moves as exp(rho) R^T. With R_c = S_c R_f,
    t_c = S_c t_f + t_s and the perturbations (exp(w) R, t + v) of the frame (f) and the sensor (s):
    camera c turns by phi = w_s + S_c w_f (camera frame), so d rho = -R_c^T phi, and its centre
    C = -R_c^T t_c moves by -R_c^T ([t_c]x phi + v_s + S_c v_f - [S_c t_f]x w_s).

    Args:
        state: The points problem's state (one frame, one image per camera).
        layout: Its reduced layout (G = layout.size).

    Returns:
        d rho / d x (C, 3, G) and d C / d x (C, 3, G).
    """
    G = layout.size
    f = state.rig_from_world[0]
    C = len(state.sensor_from_rig)
    J_rho = np.zeros((C, 3, G + 1))  # column G: the held (-1) columns, dropped
    J_C = np.zeros((C, 3, G + 1))
    fc = layout.frames[0]
    for c, s in enumerate(state.sensor_from_rig):
        Rc, tc = s.R @ f.R, s.R @ f.t + s.t
        sc = layout.sensors[c]
        # frame columns: phi = S w_f; dt = S v_f
        J_rho[c][:, fc[:3]] += -Rc.T @ s.R
        J_C[c][:, fc[:3]] += -Rc.T @ _skew(tc) @ s.R
        J_C[c][:, fc[3:]] += -Rc.T @ s.R
        if sc[0] >= 0:  # sensor columns: phi = w_s; dt = v_s - [S t_f]x w_s
            J_rho[c][:, sc[:3]] += -Rc.T
            J_C[c][:, sc[:3]] += -Rc.T @ (_skew(tc) - _skew(s.R @ f.t))
            J_C[c][:, sc[3:]] += -Rc.T
    return J_rho[:, :, :G], J_C[:, :, :G]


@dataclass(frozen=True)
class Gauge:
    """What self-calibration holds of the rig: its mean motion along the window-keeping motions, and its scale.

    The mean motion is from the start, along the motions that keep the windows (``twists``,
    :func:`window_gauge`); the scale is the sum of all pairwise camera distances.

    ``g_k = sum_c (L^2 omega_k . rho_c + (omega_k x C0_c + v_k) . (C_c - C0_c)) / norm_k`` (mm) is the
    component of the cameras' motions along gauge motion k (``L``: ``length_mm``, the rig's distance
    to the particles, weighs rotations against displacements); the rows say g = 0 and
    sum_{i<j} |C_i - C_j| = ``scale_sum_mm``, each with sigma ``STIFF_SIGMA_MM``. The ``soft`` motions'
    components are held softly, with sigma ``soft_sigma_mm``.
    """

    start_R: np.ndarray  # (C, 3, 3) the start's cam_from_world rotations
    start_centres: np.ndarray  # (C, 3)
    twists: np.ndarray  # (K, 6)
    length_mm: float
    scale_sum_mm: float
    soft: np.ndarray | None = None  # (S, 6) the other rigid motions (the rig's tilt to the windows, its distance)
    soft_sigma_mm: float = 1.0  # ... held softly: their prior's sigma

    @staticmethod
    def of(calibration: Calibration, in_air: Sequence[bool], length_mm: float) -> Gauge:
        cams = list(calibration.cameras.values())
        R = np.array([c.cam_from_world.R for c in cams])
        centres = np.array([c.cam_from_world.inverse().t for c in cams])
        normals, _ = window_planes(calibration)
        return Gauge(R, centres, window_gauge(normals, in_air), float(length_mm), pairwise_sum_mm(centres),
                     window_gauge(normals, in_air, complement=True),
                     float(length_mm) * math.radians(RIG_TILT_PRIOR_DEG))

    def _motions(self, twists: np.ndarray | None = None) -> np.ndarray:
        """(K, C, 6) each twist's motion of every camera [rho, dC], normalised to unit norm."""
        twists = self.twists if twists is None else twists
        om, v = twists[:, :3], twists[:, 3:]
        m = np.concatenate([np.broadcast_to(om[:, None, :], (len(om), len(self.start_centres), 3)),
                            np.cross(om[:, None, :], self.start_centres[None]) + v[:, None, :]], axis=2)
        norm = np.sqrt(np.sum(self.length_mm ** 2 * m[..., :3] ** 2 + m[..., 3:] ** 2, axis=(1, 2)))
        return m / norm[:, None, None]

    def rows(self, state, layout) -> tuple[np.ndarray, np.ndarray]:
        """The gauge rows, the scale row, then (with ``soft``) the soft rows, whitened.

        Args:
            state: The points problem's state.
            layout: Its reduced layout (G = layout.size).

        Returns:
            The whitened errors (K + 1 (+ S),) and their Jacobians (K + 1 (+ S), G).
        """
        R, t = camera_poses(state)
        centres = -np.einsum("cji,cj->ci", R, t)
        rho = np.array([_log_rotation(Rc.T @ R0) for Rc, R0 in zip(R, self.start_R)])
        J_rho, J_C = motion_jacobians(state, layout)
        L2 = self.length_mm ** 2

        def along(twists: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            m = self._motions(twists)
            return (np.einsum("kci,ci->k", L2 * m[..., :3], rho) + np.einsum("kci,ci->k", m[..., 3:],
                                                                              centres - self.start_centres),
                    np.einsum("kci,cig->kg", L2 * m[..., :3], J_rho) + np.einsum("kci,cig->kg", m[..., 3:], J_C))

        g, J_g = along(self.twists)
        s, ds = _pairwise_sum_gradient(centres)
        J_s = np.einsum("ci,cig->g", ds, J_C)
        e = np.append(g, s - self.scale_sum_mm) / STIFF_SIGMA_MM
        J = np.vstack([J_g, J_s[None]]) / STIFF_SIGMA_MM
        if self.soft is not None and len(self.soft):
            g_s, J_gs = along(self.soft)
            e, J = np.append(e, g_s / self.soft_sigma_mm), np.vstack([J, J_gs / self.soft_sigma_mm])
        return e, J


def pairwise_sum_mm(centres: np.ndarray) -> float:
    """Sum of the distances between every pair of camera centres (the held scale)."""
    return _pairwise_sum_gradient(np.asarray(centres, float))[0]


def _pairwise_sum_gradient(centres: np.ndarray) -> tuple[float, np.ndarray]:
    d = centres[:, None, :] - centres[None, :, :]
    n = np.linalg.norm(d, axis=2)
    iu = np.triu_indices(len(centres), 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        u = np.where(n[..., None] > 0, d / n[..., None], 0.0)
    return float(n[iu].sum()), u.sum(axis=1)


# --------------------------------------------------------------------------- intrinsics priors


@dataclass(frozen=True)
class IntrinsicsPrior:
    """The start's values of the free intrinsics and how sure it is of them.

    ``free``: the indices (of the 9) of the free intrinsics; per camera the sigmas, or (``whitening``) the
    joint covariance of every camera's free intrinsics.
    """

    free: tuple[int, ...]
    values: np.ndarray  # (C, F)
    sigmas: np.ndarray  # (C, F); inf: no prior (mode "free")
    whitening: np.ndarray | None = None  # (C F, C F) W with W^T W the inverse of the joint covariance (camera-major:
    # camera 0's F, then camera 1's, ...); None: the sigmas alone (each parameter its own prior)

    @staticmethod
    def of(calibration: Calibration, free: Sequence[int], mode: str) -> IntrinsicsPrior:
        names = list(calibration.cameras)
        values = np.array([[calibration.cameras[n].params[i] for i in free] for n in names]).reshape(len(names), -1)
        sig = np.full(values.shape, np.inf)
        if mode == "prior":
            unc = calibration.uncertainty
            guessed = guessed_principal_points(calibration)
            for c, n in enumerate(names):
                cu = None if unc is None else unc.cameras.get(n)
                for j, i in enumerate(free):
                    s = None if cu is None else cu.intrinsics.get(PARAM_NAMES[i])
                    if n in guessed and PARAM_NAMES[i] in ("cx", "cy"):
                        s = None  # held at a guess: its error is unknown, not 1e-4 px
                    fallback = UNKNOWN_PRIOR_K1 if PARAM_NAMES[i] == "k1" else UNKNOWN_PRIOR_PX
                    sig[c, j] = float(s) if s is not None and math.isfinite(s) and s > 0 else fallback
        return IntrinsicsPrior(tuple(free), values, sig)

    def with_covariance(self, covariance: np.ndarray) -> IntrinsicsPrior:
        """This prior with the joint covariance of the free intrinsics instead of the sigmas alone.

        Args:
            covariance: The joint covariance (C F, C F), camera-major.

        Returns:
            The prior, its sigmas from the covariance's diagonal and its whitening from all of it
            (:func:`whitening_of`).
        """
        return replace(self, sigmas=np.sqrt(np.diag(covariance)).reshape(self.values.shape),
                       whitening=whitening_of(covariance))

    def rows(self, state, layout, noise_px: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The prior's whitened rows, weighed against pixel residuals of ``noise_px``.

        The rows are noise_px W (p - p0); with sigmas alone W = diag(1 / sigma).

        Args:
            state: The points problem's state.
            layout: Its reduced layout.
            noise_px: The pixel noise the rows are weighed against.

        Returns:
            The whitened errors (R,), their Jacobian (R, K) and the K columns it is on.

        Raises:
            ValueError: the prior's covariance is over another number of parameters than the problem estimates.
        """
        cols, delta, w = [], [], []
        for c, ix in enumerate(layout.intrinsics):
            for j, col in enumerate(ix):
                s = self.sigmas[c, j]
                if col < 0 or not math.isfinite(s):
                    continue
                cols.append(col)
                delta.append(state.colmap_params[c][j] - self.values[c, j])
                w.append(1.0 / s)
        cols_a = np.array(cols, dtype=int)
        if not cols:
            return np.zeros(0), np.zeros((0, 0)), cols_a
        W = np.diag(w) if self.whitening is None else self.whitening
        if W.shape[1] != len(cols):
            raise ValueError(f"the intrinsics prior's covariance is over {W.shape[1]} parameters, the problem "
                             f"estimates {len(cols)}")
        J = noise_px * W
        return J @ np.array(delta), J, cols_a


def guessed_principal_points(calibration: Calibration) -> list[str]:
    """The cameras whose principal point the start held at a guess rather than estimated.

    ``calibrate`` holds it at the image centre when its views leave it undetermined: cx or cy with a sigma
    below HELD_SIGMA_PX while the focal length's is not (every intrinsic held: a K declared known,
    ``--fix-intrinsics``). Such a principal point gets the prior of an unknown (UNKNOWN_PRIOR_PX) and the
    result says so.

    Args:
        calibration: The start calibration.

    Returns:
        The cameras' names (none without the start's uncertainty).
    """
    unc = calibration.uncertainty
    if unc is None:
        return []
    out = []
    for n, cu in unc.cameras.items():
        s = cu.intrinsics
        held = [_held(s, k) for k in ("cx", "cy")]
        if any(held) and not _held(s, "fx"):
            out.append(n)
    return out


def _held(sigmas: Mapping[str, float | None], name: str) -> bool:
    """Whether parameter ``name`` has a sigma below HELD_SIGMA_PX (the start held it)."""
    sigma = sigmas.get(name)
    return sigma is not None and sigma < HELD_SIGMA_PX


def whitening_of(covariance: np.ndarray) -> np.ndarray:
    """W with W^T W = covariance^-1, computed on its correlations.

    Directions the covariance holds no variance along are given none of the information either.

    Args:
        covariance: The covariance (n, n).

    Returns:
        W (r, n), r the covariance's rank.

    Raises:
        ValueError: the covariance is not finite or its diagonal not positive.
    """
    cov = np.asarray(covariance, float)
    s = np.sqrt(np.diag(cov))
    if not (np.all(np.isfinite(cov)) and np.all(s > 0)):
        raise ValueError("the intrinsics covariance must be finite with a positive diagonal")
    corr = cov / np.outer(s, s)
    lam, V = np.linalg.eigh(0.5 * (corr + corr.T))
    keep = lam > 1e-12 * lam.max()
    return (V[:, keep] / np.sqrt(lam[keep])).T / s[None, :]


# --------------------------------------------------------------------------- the solver


class GaugeTerm(RowTerm["State"]):
    """The gauge and scale rows (:meth:`Gauge.rows`) as a term of the bundle adjustment.

    Args:
        gauge: The gauge.
        layout: The points problem's reduced layout.
    """

    def __init__(self, gauge: Gauge, layout: Layout) -> None:
        self.gauge = gauge
        self.layout = layout

    def rows(self, x: State) -> Rows:
        """The gauge's whitened rows, dense over the reduced columns.

        Args:
            x: The points problem's state.

        Returns:
            The rows.
        """
        e, J = self.gauge.rows(x, self.layout)
        return Rows(e, J, np.arange(J.shape[1]))

    def columns(self) -> np.ndarray:
        """The frames' and sensors' columns (the rows depend on the camera poses alone)."""
        cols = np.concatenate([self.layout.frames.ravel(), self.layout.sensors.ravel()])
        return cols[cols >= 0]


class IntrinsicsPriorTerm(RowTerm["State"]):
    """The start's intrinsics as a prior (:meth:`IntrinsicsPrior.rows`), weighed against ``noise_px``.

    Args:
        prior: The prior.
        layout: The points problem's reduced layout.
        noise_px: The pixel noise the rows are whitened against.
    """

    def __init__(self, prior: IntrinsicsPrior, layout: Layout, noise_px: float) -> None:
        self.prior = prior
        self.layout = layout
        self.noise_px = noise_px

    def rows(self, x: State) -> Rows:
        """The prior's whitened rows on the free intrinsics that have a prior.

        Args:
            x: The points problem's state.

        Returns:
            The rows.
        """
        e, J, cols = self.prior.rows(x, self.layout, self.noise_px)
        return Rows(e, J, cols)

    def columns(self) -> np.ndarray:
        """The columns of the free intrinsics with a finite sigma."""
        return np.array([col for c, ix in enumerate(self.layout.intrinsics) for j, col in enumerate(ix)
                         if col >= 0 and math.isfinite(self.prior.sigmas[c, j])], dtype=int)


def _solver(problem: RefractiveProblem, huber_px: float | None, gauge: Gauge, prior: IntrinsicsPrior,
            noise_px: float) -> Solver:
    """Self-calibration's bundle adjustment: refine-colmap's points problem, the window held, with the gauge
    and the intrinsics prior as terms (Marquardt's damping from the particles alone)."""
    from ..colmap.refine.solver import Solver

    terms = [GaugeTerm(gauge, problem.layout), IntrinsicsPriorTerm(prior, problem.layout, noise_px)]
    return Solver(problem, huber_px, terms=terms, damp_observations_only=True)


def _prior_term(solver: Solver) -> IntrinsicsPriorTerm:
    """The solver's intrinsics prior term."""
    return next(t for t in solver.row_terms if isinstance(t, IntrinsicsPriorTerm))


@dataclass(frozen=True)
class Covariance:
    """The adjustment's sigmas (points eliminated; the gauge and the scale held)."""

    sigma_px: float
    cameras: Mapping[str, CameraSigma]


def _sigma(J: np.ndarray, cov: np.ndarray) -> float:
    v = float(np.trace(J @ cov @ J.T))
    return math.sqrt(v) if v >= 0 and math.isfinite(v) else float("nan")


def covariance(solver, state, names: Sequence[str], system=None) -> Covariance:
    """Per camera the sigmas of its pose relative to camera 0, in the world, and of its intrinsics.

    The covariance is ``s0^2 S^-1`` (S the undamped Schur complement,
    :func:`ari_sfm.solver.schur.global_covariance`), ``s0`` the fitted noise (:func:`fitted_noise`).

    Args:
        solver: The adjustment's solver.
        state: The solution.
        names: The cameras' names, in the calibration's order.
        system: The solver's normal equations at ``state``, if LM left them (else linearized here).

    Returns:
        The fitted noise and each camera's sigmas.
    """
    from ..solver.schur import global_covariance

    lay = solver.problem.layout
    ne = solver.linearize(state) if system is None else system
    s0 = fitted_noise(solver, state)
    cov = s0 ** 2 * global_covariance(ne)  # the priors are whitened at noise_px ~ s0 (refit_noise)
    R, t = camera_poses(state)
    J_rho, J_C = motion_jacobians(state, lay)
    # camera-frame turn phi_c = -R_c rho_c; relative rotation R_c R_0^T turns by phi_c - R_rel phi_0 (camera c)
    phi = -np.einsum("cij,cjg->cig", R, J_rho)
    out = {}
    for c, n in enumerate(names):
        intr = {}
        for j, col in enumerate(lay.intrinsics[c]):
            if col >= 0:
                intr[PARAM_NAMES[_prior_term(solver).prior.free[j]]] = math.sqrt(max(cov[col, col], 0.0))
        rel_r = rel_t = None
        if c > 0:
            R_rel = R[c] @ R[0].T
            rel_r = math.degrees(_sigma(phi[c] - R_rel @ phi[0], cov))
            C0, Cc = -R[0].T @ t[0], -R[c].T @ t[c]
            x = R[0] @ (Cc - C0)  # camera c's centre in camera 0's frame
            rel_t = _sigma(-_skew(x) @ phi[0] + R[0] @ (J_C[c] - J_C[0]), cov)
        out[n] = CameraSigma(rel_r, rel_t, math.degrees(_sigma(J_rho[c], cov)), _sigma(J_C[c], cov), intr)
    return Covariance(s0, out)


def fitted_noise(solver, state) -> float:
    """The a-posteriori pixel noise per coordinate: sqrt(Huber-weighted chi^2 / degrees of freedom).

    Args:
        solver: The adjustment's solver.
        state: The solution.

    Returns:
        The noise (px); NaN without degrees of freedom.
    """
    from ..colmap.refine.problem import huber_weights

    r = solver.problem.residuals(state)
    w = huber_weights(r, solver.huber_px)
    dof = 2 * len(r) - 3 * len(state.xyz) - solver.problem.layout.size
    return float(math.sqrt(np.sum(w * np.sum(r ** 2, axis=1)) / dof)) if dof > 0 else float("nan")


# --------------------------------------------------------------------------- GTSAM


def _gtsam_refinement(solver: Solver) -> GtsamRefinement:
    """The same adjustment as a GTSAM graph: refine-colmap's, the solver's terms as factors."""
    from ..colmap.refine import gtsam_graph as gg

    return gg.GtsamRefinement(solver.problem, solver.huber_px, terms=solver.row_terms, diagonal_damping=True)


# --------------------------------------------------------------------------- the adjustment


@dataclass(frozen=True)
class Refined:
    """The corrected calibration, how the adjustment went, and its sigmas."""

    calibration: Calibration
    adjustment: Adjustment
    covariance: Covariance
    residuals_px: np.ndarray  # (M, 2) the landmarks' reprojection residuals at the solution


def refine_with_landmarks(calibration: Calibration, particles: ParticleSet, gauge: Gauge,
                          prior: IntrinsicsPrior, huber_px: float = 1.0, max_iterations: int = 50,
                          backend: str = "numpy", noise_px: float = 0.1) -> Refined:
    """``calibration`` corrected by a bundle adjustment with ``particles`` as landmarks (module docstring).

    Every camera's pose and the free intrinsics are estimated, the window held in the world, the ``gauge``
    and the scale held.

    Args:
        calibration: The start calibration.
        particles: The matched particles.
        gauge: What is held of the rig (:meth:`Gauge.of`).
        prior: The intrinsics' prior (its ``free`` the estimated intrinsics).
        huber_px: The Huber threshold (px).
        max_iterations: Cap on Levenberg-Marquardt's iterations (per solve).
        backend: "numpy" or "gtsam" (:data:`BACKENDS`).
        noise_px: The first guess of the pixel noise the priors are weighed against (refitted when the
            residuals say otherwise).

    Returns:
        The corrected calibration, the adjustment's summary, its sigmas and the residuals.

    Raises:
        AriSfmError: an unknown backend, or the gtsam backend with more than :data:`GTSAM_MAX_LANDMARKS` particles.
    """
    from ..colmap.refine.problem import RefractiveProblem, State

    t0 = time.perf_counter()
    if backend not in BACKENDS:
        raise AriSfmError(None, f"backend must be one of {', '.join(BACKENDS)} (got {backend!r})")
    if backend == "gtsam" and len(particles.xyz) > GTSAM_MAX_LANDMARKS:
        raise AriSfmError("--backend", f"gtsam solves at most {GTSAM_MAX_LANDMARKS} particles in reasonable time "
                                       f"(this round has {len(particles.xyz)}): use the numpy backend")
    names = list(calibration.cameras)
    model = landmark_model(calibration, particles, prior.free)
    windows = calibration.window_list()
    window_of = [next(k for k, w in enumerate(windows) if n in w.cameras) for n in names]
    normals, planes = window_planes(calibration)
    problem = RefractiveProblem(model, calibration.interface, "world", False, camera_windows=window_of,
                                interfaces=[w.interface for w in windows], hold_window=True,
                                held_frames=np.zeros(0, int), hold_intrinsics=not prior.free)
    state = State(model.colmap_params, model.rig_from_world, model.sensor_from_rig, normals, planes, model.xyz.copy())
    solver = _solver(problem, huber_px, gauge, prior, noise_px)
    cost0 = solver.cost(state)
    final, iterations, stop, system = state, 0, "converged", None
    for _ in range(3):  # weigh the priors against the fitted noise (one refit at most, normally)
        if backend == "numpy":
            from ..solver.levenberg_marquardt import LMParams, levenberg_marquardt

            # stop when a step lowers chi^2 (cost / noise^2) by less than CHI2_STOP: the rest is a crawl along
            # the weakly determined directions (the rig's tilt to the window, a principal point against a
            # rotation) by far less than their sigma
            stop_cost = 0.5 * CHI2_STOP * _prior_term(solver).noise_px ** 2
            res = levenberg_marquardt(solver, final, max_iterations, 0.0,
                                      LMParams(lambda_initial=LAMBDA_INITIAL, absolute_tolerance=stop_cost))
            final, system = res.x, res.system_at_x
            iterations += res.report.iterations
            stop = res.report.stop
        else:
            refinement = _gtsam_refinement(solver)
            final, its = refinement.optimize(final, max_iterations)
            iterations += its
            stop = "max_iterations" if its >= max_iterations else "converged"
            system = None
        s0 = fitted_noise(solver, final)
        if not (math.isfinite(s0) and abs(s0 / _prior_term(solver).noise_px - 1.0) > NOISE_REFIT and prior.free):
            break
        solver = _solver(problem, huber_px, gauge, prior, s0)
        system = None
    cov = covariance(solver, final, names, system)
    R, t = final.cam_from_world(model)
    cameras = {}
    for c, n in enumerate(names):
        cam = calibration.cameras[n]
        p9 = model.params9(c, final.colmap_params[c])
        cameras[n] = replace(cam, K=PinholeModel.from_params(p9).K, dist=p9[4:].copy(), cam_from_world=Pose(R[c], t[c]),
                             rmse_px=None)
    corrected = with_windows(replace(calibration, cameras=cameras), normals, planes)
    corrected = replace(corrected, model="exact" if calibration.model == "truth" else calibration.model)
    r = problem.residuals(final)
    e = np.linalg.norm(r, axis=1)
    centres = np.array([Pose(R[c], t[c]).inverse().t for c in range(len(names))])
    noise_px = _prior_term(solver).noise_px
    adjustment = Adjustment(int(len(particles.xyz)), int(len(e)), int(iterations), stop, float(cost0),
                            float(solver.cost(final)), float(np.sqrt(np.mean(e ** 2))), float(noise_px),
                            gauge.scale_sum_mm, pairwise_sum_mm(centres),
                            {n: rotation_angle_deg(calibration.cameras[n].cam_from_world.R, R[c])
                             for c, n in enumerate(names)}, time.perf_counter() - t0)
    if stop == "max_iterations":
        log.warning("self-calibration: the bundle adjustment of %d particles stopped at its %d-iteration cap "
                    "(not converged)", len(particles.xyz), max_iterations)
    log.info("self-calibration: bundle adjustment of %d particles: %.3f px RMS after %d iterations (%s)",
             len(particles.xyz), adjustment.rms_px, iterations, stop)
    return Refined(corrected, adjustment, cov, r)


def with_windows(calibration: Calibration, normals: np.ndarray, planes: np.ndarray) -> Calibration:
    """``calibration`` (its cameras already moved) with each window at ``normals``, ``planes`` in the world.

    The distances (from each window's first camera, as calibration.json gives them) follow the cameras.

    Args:
        calibration: The calibration, its cameras at their new poses.
        normals: Each window's unit normal in the world (W, 3).
        planes: Each window's near face offset (W,) (``normal . X = plane`` on the face).

    Returns:
        The calibration with its windows.
    """
    windows = []
    for w, n, h in zip(calibration.window_list(), normals, planes):
        centre = calibration.cameras[w.cameras[0]].cam_from_world.inverse().t
        d = float(h - n @ centre)
        if w.interface.distance_mm is not None:
            w = replace(w, interface=replace(w.interface, distance_mm=d), normal_world=n.copy())
        else:
            w = replace(w, normal_world=n.copy(), fixed_distance_mm=d if w.fixed_distance_mm is not None else None)
        windows.append(w)
    first = windows[0]
    return replace(calibration, interface=first.interface, normal_world=first.normal_world,
                   fixed_distance_mm=first.fixed_distance_mm, windows=tuple(windows) if calibration.windows else ())
