"""What a volume self-calibration did, as records: calibration.json's ``self_calibration`` written by
``to_json`` and read back by ``from_json`` (the same record), with the options it ran with and its
bundle adjustments' figures. Plain records: no numpy arrays, nothing computed here. The options' modes are
str enums (:class:`Intrinsics`, :class:`~ari_sfm.colmap.refine.options.Backend`): written as their strings."""
from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields
from enum import Enum
from typing import Any

from ..colmap.refine.options import Backend
from ..options import Choice


class Intrinsics(Choice):
    """What self-calibration does with the intrinsics: fx fy cx cy (k1) estimated with the start's sigmas as
    priors, held, or estimated without priors."""

    PRIOR = "prior"
    HELD = "held"
    FREE = "free"


@dataclass(frozen=True)
class SelfCalOptions:
    """What self-calibration does (defaults for the 4-camera PTV set-up of PHYSICS.md)."""

    tolerance_px: float = 5.0  # first round's matching tolerance (loose: the drift must fit in it)
    max_tolerance_px: float = 12.0  # the first round widens its tolerance up to this while it finds no peak
    final_tolerance_px: float = 0.5  # the tolerance the rounds tighten to
    min_cameras: int = 4  # cameras a match must use (4: ghosts are rare, the peak is clear)
    cells: tuple[int, int, int] = (3, 3, 3)  # sub-volumes (x, y, z) of the disparity maps
    peak_radius_px: float = 0.5  # a match is on its cell's peak within this many px in every camera
    field_radius_px: float = 1.5  # cells' peaks searched within this many px of the whole volume's peak
    max_rounds: int = 6
    min_improvement: float = 0.05  # stop when the inlier RMS falls by less than this fraction
    coarse_frames: int = 3  # at least this many frames (more while the first camera has < COARSE_IMAGES images)
    # are matched in rounds looser than COARSE_PX (the slow, ghost-ridden matching:
    # a few hundred inliers suffice for the first correction)
    max_landmarks: int = 20000  # particles in one bundle adjustment (random subset beyond)
    huber_px: float = 1.0  # Huber threshold of the bundle adjustment
    max_iterations: int = 50  # Levenberg-Marquardt iterations per round
    intrinsics: Intrinsics = Intrinsics.PRIOR  # prior: fx fy cx cy (k1) estimated, the start's sigmas as priors
    backend: Backend = Backend.NUMPY  # numpy (points Schur + the project's LM) or gtsam
    seed: int = 0  # the landmark subset
    threads: int = 2  # frames matched in parallel in this process (no Dask)

    def __post_init__(self) -> None:
        """The modes' strings converted; one that names no mode is one line of ValueError."""
        object.__setattr__(self, "intrinsics", Intrinsics.parse(self.intrinsics, "intrinsics"))
        object.__setattr__(self, "backend", Backend.parse(self.backend, "backend"))

    def to_json(self) -> dict[str, Any]:
        """The options as calibration.json's ``self_calibration.options`` holds them (modes as strings)."""
        def plain(v: Any) -> Any:
            return list(v) if isinstance(v, tuple) else v.value if isinstance(v, Enum) else v

        return {f.name: plain(getattr(self, f.name)) for f in fields(self)}

    @classmethod
    def from_json(cls, d: object) -> SelfCalOptions:
        """The options as ``to_json`` wrote them (keys this version does not know are ignored).

        Args:
            d: the JSON object.

        Returns:
            The options.

        Raises:
            ValueError: a value of the wrong type, or a mode this version does not know (naming the key).
        """
        known = {f.name: f for f in fields(cls)}
        kw: dict[str, Any] = {}  # (each value checked against its field's default type below)
        for key, value in _mapping(d, "options").items():
            if key not in known:
                continue
            default = getattr(cls, key)
            if isinstance(default, tuple):
                kw[key] = tuple(_int(v, f"options.{key}") for v in _list(value, f"options.{key}"))
            elif isinstance(default, str):
                kw[key] = _str(value, f"options.{key}")
            elif isinstance(default, bool):
                kw[key] = _bool(value, f"options.{key}")
            elif isinstance(default, int):
                kw[key] = _int(value, f"options.{key}")
            else:
                kw[key] = _num(value, f"options.{key}")
        return cls(**kw)


@dataclass(frozen=True)
class BeforeAfter:
    """A camera's disparity RMS (px) with the starting and the corrected calibration."""

    before: float
    after: float


@dataclass(frozen=True)
class Check:
    """One of the result's trust checks: its value against its limit, and what it means."""

    name: str
    value: float
    limit: float
    passed: bool
    what: str
    fatal: bool = True  # False: a warning only

    def to_json(self) -> dict[str, Any]:
        return {"name": self.name, "value": self.value, "limit": self.limit, "passed": self.passed,
                "fatal": self.fatal, "what": self.what}

    @classmethod
    def from_json(cls, d: object) -> Check:
        d = _mapping(d, "checks[]")
        return cls(_str(d.get("name"), "checks[].name"), _num(d.get("value"), "checks[].value"),
                   _num(d.get("limit"), "checks[].limit"), _bool(d.get("passed"), "checks[].passed"),
                   _str(d.get("what"), "checks[].what"), _bool(d.get("fatal", True), "checks[].fatal"))


@dataclass(frozen=True)
class Adjustment:
    """One bundle adjustment with the particles as landmarks
    (:func:`ari_sfm.particles.landmarks.refine_with_landmarks`)."""

    landmarks: int
    observations: int
    iterations: int
    stop: str  # Levenberg-Marquardt's stop reason ("max_iterations": it did not converge)
    cost_start: float
    cost_final: float
    rms_px: float
    noise_px: float  # the fitted pixel noise per coordinate (a-posteriori sigma) the priors were weighed with
    sum_baselines_held_mm: float  # the scale row's value: the sum of all pairwise camera distances
    sum_baselines_final_mm: float
    rotation_change_deg: Mapping[str, float]
    time_s: float

    def to_json(self) -> dict[str, Any]:
        return {"landmarks": self.landmarks, "observations": self.observations, "iterations": self.iterations,
                "stop": self.stop, "cost": {"start": self.cost_start, "final": self.cost_final},
                "rms_px": self.rms_px, "noise_px": self.noise_px,
                "sum_baselines_mm": {"held": self.sum_baselines_held_mm, "final": self.sum_baselines_final_mm},
                "rotation_change_deg": dict(self.rotation_change_deg), "time_s": self.time_s}

    @classmethod
    def from_json(cls, d: object) -> Adjustment:
        d = _mapping(d, "rounds[].adjustment")
        cost = _mapping(d.get("cost"), "adjustment.cost")
        sums = _mapping(d.get("sum_baselines_mm"), "adjustment.sum_baselines_mm")
        return cls(_int(d.get("landmarks"), "adjustment.landmarks"),
                   _int(d.get("observations"), "adjustment.observations"),
                   _int(d.get("iterations"), "adjustment.iterations"), _str(d.get("stop"), "adjustment.stop"),
                   _num(cost.get("start"), "adjustment.cost.start"), _num(cost.get("final"), "adjustment.cost.final"),
                   _num(d.get("rms_px"), "adjustment.rms_px"), _num(d.get("noise_px"), "adjustment.noise_px"),
                   _num(sums.get("held"), "adjustment.sum_baselines_mm.held"),
                   _num(sums.get("final"), "adjustment.sum_baselines_mm.final"),
                   _numbers(d.get("rotation_change_deg"), "adjustment.rotation_change_deg"),
                   _num(d.get("time_s"), "adjustment.time_s"))


@dataclass(frozen=True)
class CameraSigma:
    """One camera's 1-sigma after self-calibration: its rotation and centre relative to camera 0
    (sqrt of the covariance's trace), in the world (the window's frame) and its free intrinsics."""

    rotation_rel_deg: float | None
    translation_rel_mm: float | None
    rotation_deg: float
    centre_mm: float
    intrinsics: Mapping[str, float]

    def to_json(self) -> dict[str, Any]:
        return {"rotation_rel_deg": self.rotation_rel_deg, "translation_rel_mm": self.translation_rel_mm,
                "rotation_world_deg": self.rotation_deg, "centre_world_mm": self.centre_mm,
                "intrinsics": dict(self.intrinsics)}

    @classmethod
    def from_json(cls, d: object) -> CameraSigma:
        d = _mapping(d, "sigmas[camera]")
        return cls(_optional_num(d.get("rotation_rel_deg"), "sigmas.rotation_rel_deg"),
                   _optional_num(d.get("translation_rel_mm"), "sigmas.translation_rel_mm"),
                   _num(d.get("rotation_world_deg"), "sigmas.rotation_world_deg"),
                   _num(d.get("centre_world_mm"), "sigmas.centre_world_mm"),
                   _numbers(d.get("intrinsics", {}), "sigmas.intrinsics"))


@dataclass(frozen=True)
class RoundSummary:
    """One round as the report keeps it: its tolerance, its matches and the inliers on the disparity
    peaks, each camera's disparity RMS with the calibration it started from, and the bundle adjustment
    that followed (None for the final check)."""

    tolerance_px: float
    matches: int
    inliers: int
    disparity_rms_px: tuple[float, ...]
    adjustment: Adjustment | None

    def to_json(self) -> dict[str, Any]:
        return {"tolerance_px": self.tolerance_px, "matches": self.matches, "inliers": self.inliers,
                "disparity_rms_px": list(self.disparity_rms_px),
                "adjustment": None if self.adjustment is None else self.adjustment.to_json()}

    @classmethod
    def from_json(cls, d: object) -> RoundSummary:
        d = _mapping(d, "rounds[]")
        adjustment = d.get("adjustment")
        return cls(_num(d.get("tolerance_px"), "rounds[].tolerance_px"), _int(d.get("matches"), "rounds[].matches"),
                   _int(d.get("inliers"), "rounds[].inliers"),
                   tuple(_num(v, "rounds[].disparity_rms_px") if v is not None else math.nan
                         for v in _list(d.get("disparity_rms_px"), "rounds[].disparity_rms_px")),
                   None if adjustment is None else Adjustment.from_json(adjustment))


@dataclass(frozen=True)
class SelfCalInputs:
    """The files a dataset's self-calibration read (:func:`ari_sfm.particles.selfcal.self_calibrate_dataset`),
    absolute."""

    dataset: str
    calibration: str
    detections: str
    workers: int | None  # None with a scheduler
    scheduler: str | None


@dataclass(frozen=True)
class SelfCalReport:
    """What self-calibration did: calibration.json's ``self_calibration`` (``to_json``, ``from_json``)."""

    frames: tuple[int, ...]
    particles_used: int  # landmarks of the largest round
    landmarks_all_rounds: int
    held: tuple[str, ...]  # what was not estimated, in words
    estimated: tuple[str, ...]
    scale_how: str
    scale_sum_mm: float
    scale_sigma_mm: float
    backend: str
    options: SelfCalOptions
    disparity_rms_px: Mapping[str, BeforeAfter]
    converged: bool  # the final disparities are one noise level (:func:`ari_sfm.particles.selfcal.converged`)
    passed: bool  # every fatal trust check passed (:func:`ari_sfm.particles.selfcal.trust_checks`)
    checks: tuple[Check, ...]
    rounds: tuple[RoundSummary, ...]
    rotation_change_deg: Mapping[str, float]
    sigmas: Mapping[str, CameraSigma]
    matched_share: float  # of the final matching (trust)
    time_s: float
    inputs: SelfCalInputs | None = None  # from a dataset's files

    def to_json(self) -> dict[str, Any]:
        out = {"frames": list(self.frames), "particles_used": self.particles_used,
               "landmarks_all_rounds": self.landmarks_all_rounds, "held": list(self.held),
               "estimated": list(self.estimated),
               "scale": {"how": self.scale_how, "sum_mm": self.scale_sum_mm, "sigma_mm": self.scale_sigma_mm},
               "backend": self.backend, "options": self.options.to_json(),
               "disparity_rms_px": {n: {"before": d.before, "after": d.after}
                                    for n, d in self.disparity_rms_px.items()},
               "converged": self.converged, "passed": self.passed, "checks": [c.to_json() for c in self.checks],
               "matched_share": self.matched_share, "rounds": [r.to_json() for r in self.rounds],
               "rotation_change_deg": dict(self.rotation_change_deg),
               "sigmas": {n: s.to_json() for n, s in self.sigmas.items()}, "time_s": self.time_s}
        if self.inputs is not None:
            i = self.inputs
            out.update({"dataset": i.dataset, "calibration": i.calibration, "detections": i.detections,
                        "workers": i.workers, "scheduler": i.scheduler})
        return out

    @classmethod
    def from_json(cls, d: object) -> SelfCalReport:
        """The record ``to_json`` wrote; ValueError naming the key when it is not one."""
        d = _mapping(d, "self_calibration")
        scale = _mapping(d.get("scale"), "scale")
        inputs = None
        if "dataset" in d:
            workers = d.get("workers")
            scheduler = d.get("scheduler")
            inputs = SelfCalInputs(_str(d.get("dataset"), "dataset"), _str(d.get("calibration"), "calibration"),
                                   _str(d.get("detections"), "detections"),
                                   None if workers is None else _int(workers, "workers"),
                                   None if scheduler is None else _str(scheduler, "scheduler"))
        ba = _mapping(d.get("disparity_rms_px"), "disparity_rms_px")
        return cls(
            frames=tuple(_int(f, "frames") for f in _list(d.get("frames"), "frames")),
            particles_used=_int(d.get("particles_used"), "particles_used"),
            landmarks_all_rounds=_int(d.get("landmarks_all_rounds"), "landmarks_all_rounds"),
            held=tuple(_str(s, "held") for s in _list(d.get("held"), "held")),
            estimated=tuple(_str(s, "estimated") for s in _list(d.get("estimated"), "estimated")),
            scale_how=_str(scale.get("how"), "scale.how"), scale_sum_mm=_num(scale.get("sum_mm"), "scale.sum_mm"),
            scale_sigma_mm=_num(scale.get("sigma_mm"), "scale.sigma_mm"), backend=_str(d.get("backend"), "backend"),
            options=SelfCalOptions.from_json(d.get("options", {})),
            disparity_rms_px={str(n): BeforeAfter(_num(_mapping(v, "disparity_rms_px").get("before"),
                                                       f"disparity_rms_px.{n}.before"),
                                                  _num(_mapping(v, "disparity_rms_px").get("after"),
                                                       f"disparity_rms_px.{n}.after")) for n, v in ba.items()},
            converged=_bool(d.get("converged"), "converged"), passed=_bool(d.get("passed"), "passed"),
            checks=tuple(Check.from_json(c) for c in _list(d.get("checks"), "checks")),
            rounds=tuple(RoundSummary.from_json(r) for r in _list(d.get("rounds"), "rounds")),
            rotation_change_deg=_numbers(d.get("rotation_change_deg"), "rotation_change_deg"),
            sigmas={str(n): CameraSigma.from_json(v) for n, v in _mapping(d.get("sigmas"), "sigmas").items()},
            matched_share=_num(d.get("matched_share"), "matched_share"), time_s=_num(d.get("time_s"), "time_s"),
            inputs=inputs)


# --------------------------------------------------------------------------- reading JSON values


def _mapping(v: object, key: str) -> Mapping[str, object]:
    if not isinstance(v, Mapping):
        raise ValueError(f"{key} must be a mapping")
    return v


def _list(v: object, key: str) -> list[object]:
    if not isinstance(v, list):
        raise ValueError(f"{key} must be a list")
    return v


def _num(v: object, key: str) -> float:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        raise ValueError(f"{key} must be a number")
    return float(v)


def _optional_num(v: object, key: str) -> float | None:
    return None if v is None else _num(v, key)


def _int(v: object, key: str) -> int:
    if isinstance(v, bool) or not isinstance(v, int):
        raise ValueError(f"{key} must be an integer")
    return int(v)


def _str(v: object, key: str) -> str:
    if not isinstance(v, str):
        raise ValueError(f"{key} must be a string")
    return v


def _bool(v: object, key: str) -> bool:
    if not isinstance(v, bool):
        raise ValueError(f"{key} must be true or false")
    return v


def _numbers(v: object, key: str) -> dict[str, float]:
    return {str(k): _num(x, f"{key}.{k}") for k, x in _mapping(v, key).items()}
