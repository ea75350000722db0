"""Which calibration and which dataset produced a result, and whether they are the ones at hand.

``reconstruct`` records a ``provenance`` mapping in points.json and metrics.json::

    {"calibration": {"path": <absolute>, "sha256": <of the file's bytes>, "model": "ari"},
     "dataset": {"path": <absolute folder>, "rig": <absolute rig file>, "rig_sha256": <of its bytes>,
                 "observations_sha256": <of the corners>, "images_sha256": <of the image files' names and sizes>}}

``report`` and ``export-colmap`` compare it with the calibration.json and the
dataset they are given (:func:`calibration_mismatch`, :func:`dataset_mismatch`),
so an older reconstruction is not shown under a newer calibration, nor a
dataset of another rig or another capture (a byte-identical rig.yaml with
other corners or images) under either, without saying so. A calibration.json
records no provenance of its own: :func:`observations_mismatch` judges by its
residuals whether a dataset's corners are the ones it was calibrated on.
"""
from __future__ import annotations

import hashlib
import os
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .records import Dataset, Observation, Target

if TYPE_CHECKING:
    from .calibration.record import Calibration


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def calibration_record(path: str | Path, model: str) -> dict[str, Any]:
    """Build the ``provenance.calibration`` mapping of a calibration file.

    Args:
        path: the calibration.json file.
        model: the model of the calibration used (``ari``, ``exact``, ...).

    Returns:
        ``{"path": <absolute>, "sha256": <of the file's bytes>, "model": model}``.
    """
    return {"path": os.path.abspath(path), "sha256": file_sha256(path), "model": model}


def observations_sha256(observations: Sequence[Observation]) -> str:
    """Hash the corners themselves, whatever file they came from.

    The hash covers each observation's camera, set, frame, added_mm, ids and pixels, independent of the
    observations' order.

    Args:
        observations: the corners.

    Returns:
        The hex SHA-256.
    """
    digest = hashlib.sha256()
    for o in sorted(observations, key=lambda o: (o.set, o.frame, o.camera, o.added_mm or 0.0)):
        digest.update(f"{o.camera}\0{o.set}\0{o.frame}\0{o.added_mm!r}\0".encode())
        digest.update(np.ascontiguousarray(o.ids, dtype=np.int64).tobytes())
        digest.update(np.ascontiguousarray(o.pixels, dtype=np.float64).tobytes())
    return digest.hexdigest()


def images_sha256(dataset: Dataset) -> str | None:
    """Hex SHA-256 of the dataset's image list (names and byte sizes; cheap for thousands of images), or None."""
    listed = sorted((e.set, e.key, camera, str(path)) for e in dataset.entries() for camera, path in e.images.items())
    if not listed:
        return None
    digest = hashlib.sha256()
    for *names, path in listed:
        size = os.path.getsize(path) if os.path.isfile(path) else -1
        digest.update(("\0".join([*names, os.path.basename(path), str(size)]) + "\n").encode())
    return digest.hexdigest()


def dataset_record(dataset: Dataset) -> dict[str, Any]:
    """The ``provenance.dataset`` mapping of a loaded dataset."""
    record = {"path": str(Path(os.path.abspath(dataset.root))), "rig": str(Path(os.path.abspath(dataset.rig_path))),
              "rig_sha256": file_sha256(dataset.rig_path)}
    if dataset.observations is not None:
        record["observations_sha256"] = observations_sha256(dataset.observations)
    images = images_sha256(dataset)
    if images is not None:
        record["images_sha256"] = images
    return record


def provenance(calibration_path: str | Path, model: str, dataset: Dataset) -> dict[str, Any]:
    """Build the ``provenance`` mapping written into points.json and metrics.json.

    Args:
        calibration_path: the calibration.json the result was made with.
        model: the model of that calibration used.
        dataset: the dataset the result was made from.

    Returns:
        ``{"calibration": ..., "dataset": ...}`` (see the module's docstring).
    """
    return {"calibration": calibration_record(calibration_path, model), "dataset": dataset_record(dataset)}


def _recorded(result: Mapping[str, Any] | None, part: str) -> Mapping[str, Any] | None:
    prov = result.get("provenance") if isinstance(result, Mapping) else None
    rec = prov.get(part) if isinstance(prov, Mapping) else None
    return rec if isinstance(rec, Mapping) else None


def calibration_mismatch(result: Mapping[str, Any] | None, calibration_path: str | Path,
                         model: str | None = None) -> str | None:
    """Say why a result was not made with a calibration file.

    Decided by the recorded content hash; for a result that records no provenance, by the model name it
    holds (``model`` key), if any.

    Args:
        result: the content of points.json or metrics.json (None: nothing recorded).
        calibration_path: the calibration.json at hand.
        model: the model of that calibration, None if unknown.

    Returns:
        One line saying what differs, or None when the result matches or nothing tells.
    """
    rec = _recorded(result, "calibration")
    if rec is not None and isinstance(rec.get("sha256"), str):
        if rec["sha256"] == file_sha256(calibration_path):
            return None
        return (f"made with another calibration ({rec.get('path')}, model {rec.get('model')}, sha256 "
                f"{rec['sha256'][:12]}) than {calibration_path} (model {model}, sha256 "
                f"{file_sha256(calibration_path)[:12]})")
    made_with = result.get("model") if isinstance(result, Mapping) else None
    if isinstance(made_with, str) and model is not None and made_with != model:
        return f"made with a model {made_with} calibration, but {calibration_path} is model {model}"
    return None


def dataset_mismatch(result: Mapping[str, Any] | None, dataset: Dataset) -> str | None:
    """Say why a result was not made from a dataset.

    A result differs when it records another rig file content, other corners or another image list.

    Args:
        result: the content of points.json or metrics.json (None: nothing recorded).
        dataset: the dataset at hand.

    Returns:
        One line saying what differs, or None when the result matches or records no dataset.
    """
    rec = _recorded(result, "dataset")
    if rec is None or not isinstance(rec.get("rig_sha256"), str):
        return None
    if rec["rig_sha256"] != file_sha256(dataset.rig_path):
        return (f"made from the dataset {rec.get('path')} (rig sha256 {rec['rig_sha256'][:12]}), not from "
                f"{dataset.root} (rig sha256 {file_sha256(dataset.rig_path)[:12]})")
    now = dataset_record(dataset)
    for key, what in (("observations_sha256", "corners"), ("images_sha256", "images")):
        if isinstance(rec.get(key), str) and key in now and rec[key] != now[key]:
            return (f"made from other {what} than {dataset.root}'s (the same rig.yaml, another capture: {key} "
                    f"{rec[key][:12]}, now {now[key][:12]})")
    return None


RESIDUAL_MISMATCH_FACTOR = 5.0  # a dataset's corners at the calibration's own poses: rmse above
RESIDUAL_MISMATCH_PX = 2.0  # factor x recorded + px: not the corners it was calibrated on


def observations_mismatch(calibration: Calibration, observations: Sequence[Observation],
                          target: Target | None = None) -> str | None:
    """Say why observations are not the corners a calibration was made from.

    They are not when their rmse at the calibration's own frame poses is far above the rmse it records
    (above :data:`RESIDUAL_MISMATCH_FACTOR` x recorded + :data:`RESIDUAL_MISMATCH_PX`).

    Args:
        calibration: the calibration.
        observations: the dataset's corners; only the calibration and stacking sets are judged.
        target: the target the corners belong to; None for the calibration's own.

    Returns:
        One line saying what differs, or None when the corners fit, the calibration records no rmse, or
        no frame of it is observed.
    """
    from .calibration.evaluate import reprojection_stats  # the raw statistics (count 0, NaN), no error

    recorded = calibration.residuals.rmse_px if calibration.residuals is not None else None
    target = target or calibration.target
    if recorded is None or target is None:
        return None
    held = [o for o in observations if o.set in ("calibration", "stacking")]
    stats = reprojection_stats(calibration, held, target)
    if stats.count == 0 or stats.rmse_px <= RESIDUAL_MISMATCH_FACTOR * recorded + RESIDUAL_MISMATCH_PX:
        return None  # (NaN compares False: a corner that projects to no pixel is a mismatch)
    at = f"rmse {stats.rmse_px:.4g} px" if np.isfinite(stats.rmse_px) else "corners that project to no pixel"
    return (f"its corners are not the ones the calibration was made from: {at} at the calibration's frame poses, "
            f"{recorded:.4g} px recorded (the same rig, another capture?)")


def recorded_dataset_path(result: Mapping[str, Any] | None) -> Path | None:
    """The absolute dataset folder a result records, or None."""
    rec = _recorded(result, "dataset")
    path = rec.get("path") if rec is not None else None
    return Path(path) if isinstance(path, str) and os.path.isabs(path) else None
