"""Which calibration and which dataset produced a result, and whether they are the ones at hand.

``reconstruct`` records a ``provenance`` mapping in points.json and metrics.json::

    {"calibration": {"path": <absolute>, "sha256": <of the file's bytes>, "model": "ari"},
     "dataset": {"path": <absolute folder>, "rig": <absolute rig file>, "rig_sha256": <of its bytes>}}

``report`` and ``export-colmap`` compare it with the calibration.json and the
dataset they are given (:func:`calibration_mismatch`, :func:`dataset_mismatch`),
so an older reconstruction is not shown under a newer calibration, nor a
dataset of another rig under either, without saying so.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any, Mapping

from .records import Dataset


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def calibration_record(path: str | Path, model: str) -> dict[str, Any]:
    """The ``provenance.calibration`` mapping of a calibration file."""
    return {"path": os.path.abspath(path), "sha256": file_sha256(path), "model": model}


def dataset_record(dataset: Dataset) -> dict[str, Any]:
    """The ``provenance.dataset`` mapping of a loaded dataset."""
    return {"path": str(Path(os.path.abspath(dataset.root))), "rig": str(Path(os.path.abspath(dataset.rig_path))),
            "rig_sha256": file_sha256(dataset.rig_path)}


def provenance(calibration_path: str | Path, model: str, dataset: Dataset) -> dict[str, Any]:
    """The ``provenance`` mapping written into points.json and metrics.json."""
    return {"calibration": calibration_record(calibration_path, model), "dataset": dataset_record(dataset)}


def _recorded(result: Mapping[str, Any] | None, part: str) -> Mapping[str, Any] | None:
    prov = result.get("provenance") if isinstance(result, Mapping) else None
    rec = prov.get(part) if isinstance(prov, Mapping) else None
    return rec if isinstance(rec, Mapping) else None


def calibration_mismatch(result: Mapping[str, Any] | None, calibration_path: str | Path,
                         model: str | None = None) -> str | None:
    """Why ``result`` (points.json / metrics.json content) was not made with ``calibration_path``, or None.

    Decided by the recorded content hash; for a result written before provenance
    was recorded, by the model name it holds (``model`` key), if any.
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
    """Why ``result`` was not made from ``dataset`` (another rig file content), or None (also when unrecorded)."""
    rec = _recorded(result, "dataset")
    if rec is None or not isinstance(rec.get("rig_sha256"), str):
        return None
    if rec["rig_sha256"] == file_sha256(dataset.rig_path):
        return None
    return (f"made from the dataset {rec.get('path')} (rig sha256 {rec['rig_sha256'][:12]}), not from "
            f"{dataset.root} (rig sha256 {file_sha256(dataset.rig_path)[:12]})")


def recorded_dataset_path(result: Mapping[str, Any] | None) -> Path | None:
    """The absolute dataset folder a result records, or None."""
    rec = _recorded(result, "dataset")
    path = rec.get("path") if rec is not None else None
    return Path(path) if isinstance(path, str) and os.path.isabs(path) else None
