"""Data-contract I/O (see DATASET_FORMAT.md): rig files, calibration.json, observations, points, atomic writes.

Every ``load_*`` validates its file fully and raises
:class:`~ari_sfm.errors.AriSfmError` (file + one-line message); every ``save_*``
validates first and writes atomically.
"""
from __future__ import annotations

from ari_sfm.io.atomic import (
    exclusive_folder,
    write_bytes_atomic,
    write_files_atomic,
    write_json_atomic,
    write_text_atomic,
)
from ari_sfm.io.calibration_file import calibration_to_json, load_calibration, parse_calibration, save_calibration
from ari_sfm.io.dataset import detections_rig, dump_rig, find_rig, load_dataset, save_detections, save_rig
from ari_sfm.io.observations import load_observations, save_observations
from ari_sfm.io.points import load_points, save_points
from ari_sfm.io.structured import (
    as_finite_float,
    as_float_array,
    as_float_at_least,
    as_int,
    as_int_array,
    as_int_pair,
    as_list,
    as_mapping,
    as_name,
    as_nonnegative_float,
    as_positive_float,
    as_str,
    read_structured,
    require,
)

__all__ = [
    "as_finite_float",
    "as_float_array",
    "as_float_at_least",
    "as_int",
    "as_int_array",
    "as_int_pair",
    "as_list",
    "as_mapping",
    "as_name",
    "as_nonnegative_float",
    "as_positive_float",
    "as_str",
    "calibration_to_json",
    "detections_rig",
    "dump_rig",
    "find_rig",
    "load_calibration",
    "load_dataset",
    "load_observations",
    "load_points",
    "parse_calibration",
    "read_structured",
    "require",
    "save_calibration",
    "save_observations",
    "save_points",
    "save_detections",
    "save_rig",
    "write_bytes_atomic",
    "write_files_atomic",
    "exclusive_folder",
    "write_json_atomic",
    "write_text_atomic",
]
