"""Data-contract I/O: round trips, the DATASET_FORMAT.md example, and one test per bad input."""
from __future__ import annotations

import json
import os
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest
import yaml

from ari_sfm.errors import AriSfmError
from ari_sfm.io import (
    dump_rig,
    load_dataset,
    load_observations,
    load_points,
    read_structured,
    save_observations,
    save_points,
    save_rig,
    write_json_atomic,
    write_text_atomic,
)
from ari_sfm.records import CameraSpec, Dataset, Entry, Interface, Observation, Target

# The rig example of DATASET_FORMAT.md, verbatim.
EXAMPLE_RIG = """\
format: ari-sfm/1
target:
  type: checkerboard
  inner_corners: [11, 8]
  square_mm: 10.0
interface:                 # the window that every camera looks through
  thickness_mm: 50.0       # measured or from the manufacturer
  index: 1.5168
  medium_index: 1.0        # optional, default 1.0
cameras:
  cam0: {image_size: [2448, 2048]}   # optional hints: focal_px, K, dist
  cam1: {image_size: [2448, 2048]}
stacking:                  # optional: glass plates of the same glass added
  - pose: s0               # in front of the window, target not moved;
    added_mm: 0            # one entry per plate stack and pose
    images: {cam0: stack/cam0_s0_00.png, cam1: stack/cam1_s0_00.png}
  - pose: s0
    added_mm: 10
    images: {cam0: stack/cam0_s0_10.png, cam1: stack/cam1_s0_10.png}
calibration:               # target poses; every camera that saw the pose
  - frame: f000            # lists its image
    images: {cam0: calib/cam0_000.png, cam1: calib/cam1_000.png}
reconstruction:            # optional: target poses to reconstruct for the
  - frame: r000            # accuracy report
    stage_mm: 0.0          # optional: known translation along a line
    images: {cam0: recon/cam0_000.png, cam1: recon/cam1_000.png}
observations: observations.json   # optional: detections instead of images
"""

# The observations example of DATASET_FORMAT.md with its "[...]" filled in.
EXAMPLE_OBSERVATIONS = """\
{"format": "ari-sfm-observations/1",
 "observations": [
   {"camera": "cam0", "set": "stacking", "pose": "s0", "added_mm": 10,
    "ids": [0, 1, 2], "pixels": [[1021.53, 733.02], [1110.87, 734.11], [1200.2, 735.3]]},
   {"camera": "cam0", "set": "calibration", "frame": "f000",
    "ids": [0, 1], "pixels": [[1021.5, 733.0], [1110.8, 734.1]]},
   {"camera": "cam1", "set": "reconstruction", "frame": "r000", "stage_mm": 2.0,
    "ids": [0, 1], "pixels": [[1000.25, 700.5], [1090.75, 701.0]]}
 ]}
"""

EXAMPLE_POINTS = """\
{"format": "ari-sfm-points/1",
 "calibration": "calibration.json",
 "frames": {"r000": {"stage_mm": 0.0, "ids": [0, 1],
                     "xyz": [[10.0, 0.1, 499.8], [20.0, 0.1, 499.9]],
                     "ray_gap_mm": [0.004, 0.006]}}}
"""


def write_example(folder: Path, rig: str = EXAMPLE_RIG, observations: str | None = EXAMPLE_OBSERVATIONS) -> Path:
    """The example dataset with empty dummy images; returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "rig.yaml").write_text(rig)
    example = yaml.safe_load(EXAMPLE_RIG)
    for entry in example["stacking"] + example["calibration"] + example["reconstruction"]:
        for rel in entry["images"].values():
            (folder / rel).parent.mkdir(parents=True, exist_ok=True)
            (folder / rel).write_bytes(b"")
    if observations is not None:
        (folder / "observations.json").write_text(observations)
    return folder


def assert_records_equal(a, b) -> None:
    """Field-by-field equality of records, mappings, sequences and arrays."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        assert isinstance(a, np.ndarray) and isinstance(b, np.ndarray)
        assert a.dtype.kind == b.dtype.kind and a.shape == b.shape
        np.testing.assert_array_equal(a, b)
    elif hasattr(a, "__dataclass_fields__"):
        assert type(a) is type(b)
        for f in fields(a):
            assert_records_equal(getattr(a, f.name), getattr(b, f.name))
    elif isinstance(a, dict):
        assert isinstance(b, dict) and list(a) == list(b)
        for k in a:
            assert_records_equal(a[k], b[k])
    elif isinstance(a, (list, tuple)):
        assert type(a) is type(b) and len(a) == len(b)
        for x, y in zip(a, b):
            assert_records_equal(x, y)
    else:
        assert a == b and type(a) is type(b), (a, b)


# --------------------------------------------------------------------------- the example


def test_example_dataset_loads(tmp_path: Path) -> None:
    ds = load_dataset(write_example(tmp_path / "ds"))
    assert ds.rig_path == tmp_path / "ds" / "rig.yaml"
    assert ds.target == Target(type="checkerboard", inner_corners=(11, 8), square_mm=10.0)
    assert ds.target.num_ids() == 88
    assert ds.interface == Interface(thickness_mm=50.0, index=1.5168, medium_index=1.0)
    assert list(ds.cameras) == ["cam0", "cam1"] and ds.cameras["cam1"].image_size == (2448, 2048)
    assert [(e.key, e.added_mm) for e in ds.stacking] == [("s0", 0.0), ("s0", 10.0)]
    assert ds.calibration[0].images["cam1"] == tmp_path / "ds" / "calib" / "cam1_000.png"
    assert ds.reconstruction[0].stage_mm == 0.0
    assert ds.observations_path == tmp_path / "ds" / "observations.json"
    obs = ds.observations
    assert [(o.camera, o.set, o.frame, o.added_mm, o.stage_mm) for o in obs] == [
        ("cam0", "stacking", "s0", 10.0, None),
        ("cam0", "calibration", "f000", None, None),
        ("cam1", "reconstruction", "r000", None, 2.0),
    ]
    assert obs[0].ids.dtype == np.int64 and obs[0].pixels.shape == (3, 2)
    assert obs[0].pixels[0, 0] == 1021.53


def test_example_dataset_loads_from_rig_file_and_json(tmp_path: Path) -> None:
    folder = write_example(tmp_path / "ds")
    assert load_dataset(folder / "rig.yaml").rig_path.name == "rig.yaml"
    (folder / "rig.yaml").unlink()
    (folder / "rig.json").write_text(json.dumps(yaml.safe_load(EXAMPLE_RIG)))
    ds = load_dataset(folder)
    assert ds.rig_path.name == "rig.json" and len(ds.calibration) == 1


def _observations_only_folder(tmp_path: Path, extra_record: dict | None = None,
                              drop_sets: tuple[str, ...] = ()) -> Path:
    """The example rig without images (minus ``drop_sets``), its observations plus ``extra_record``."""
    rig = yaml.safe_load(EXAMPLE_RIG)
    for set_name in ("stacking", "calibration", "reconstruction"):
        for entry in rig[set_name]:
            del entry["images"]
    rig["stacking"] = rig["stacking"][1:]  # s0 / 10 mm has a record
    for set_name in drop_sets:
        del rig[set_name]
    folder = tmp_path / "ds"
    folder.mkdir()
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig))
    obs = json.loads(EXAMPLE_OBSERVATIONS)
    if extra_record is not None:
        obs["observations"].append(extra_record)
    (folder / "observations.json").write_text(json.dumps(obs))
    return folder


def test_observations_only_dataset(tmp_path: Path) -> None:
    """Entries without images, their detections in observations.json: accepted."""
    ds = load_dataset(_observations_only_folder(tmp_path))
    assert all(not e.images for e in ds.entries())
    assert [o.frame for o in ds.observations] == ["s0", "f000", "r000"]


def test_observations_of_a_set_the_rig_does_not_list_are_accepted(tmp_path: Path) -> None:
    """A set absent from rig.yaml is taken from observations.json alone (as a rig without entries)."""
    ds = load_dataset(_observations_only_folder(
        tmp_path, {"camera": "cam1", "set": "calibration", "frame": "f999", "ids": [], "pixels": []},
        drop_sets=("calibration",)))
    assert ds.calibration == () and ds.observations[-1].frame == "f999"
    assert ds.observations[-1].pixels.shape == (0, 2)


@pytest.mark.parametrize("record, what", [
    ({"camera": "cam1", "set": "calibration", "frame": "f999", "ids": [0], "pixels": [[5.0, 5.0]]},
     "frame 'f999' is not listed in calibration"),
    ({"camera": "cam1", "set": "reconstruction", "frame": "r00O", "ids": [0], "pixels": [[5.0, 5.0]]},
     "frame 'r00O' is not listed in reconstruction"),
    ({"camera": "cam1", "set": "stacking", "pose": "s0", "added_mm": 20, "ids": [0], "pixels": [[5.0, 5.0]]},
     "pose 's0' with added_mm 20 is not listed in stacking"),
])
def test_observation_of_an_undeclared_frame_is_an_error(tmp_path: Path, record: dict, what: str) -> None:
    """A typo in a frame name would split one pose in two: one line naming the frame and both files."""
    folder = _observations_only_folder(tmp_path, record)
    with pytest.raises(AriSfmError) as info:
        load_dataset(folder)
    assert info.value.path.endswith("observations.json") and what in info.value.message
    assert "rig.yaml" in info.value.message and "\n" not in str(info.value)


def test_dataset_with_only_observations_and_no_entries(tmp_path: Path) -> None:
    rig = yaml.safe_load(EXAMPLE_RIG)
    for set_name in ("stacking", "calibration", "reconstruction"):
        del rig[set_name]
    folder = tmp_path / "ds"
    folder.mkdir()
    (folder / "rig.yaml").write_text(yaml.safe_dump(rig))
    (folder / "observations.json").write_text(EXAMPLE_OBSERVATIONS)
    ds = load_dataset(folder)
    assert ds.entries() == () and len(ds.observations) == 3


# --------------------------------------------------------------------------- round trips


def _rich_dataset(tmp_path: Path) -> Dataset:
    """A dataset using every optional field (charuco target, hints, stage, observations)."""
    root = tmp_path / "src"
    images = {}
    for name in ("a/c0_0.png", "a/c1_0.png", "b/c0_1.png"):
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_bytes(b"x")
        images[name] = root / name
    K = np.array([[3478.31234567891, 0.0, 1224.1], [0.0, 3478.2, 1023.8], [0.0, 0.0, 1.0]])
    cams = {
        "cam0": CameraSpec("cam0", (2448, 2048), focal_px=3478.3, K=K, dist=np.array([0.1, -0.2, 1e-4, 2e-5, 0.3])),
        "cam1": CameraSpec("cam1", (1920, 1080)),
    }
    rng = np.random.default_rng(0)
    obs = (
        Observation("cam0", "stacking", "s0", np.array([0, 5, 7]), rng.uniform(0, 1000, (3, 2)), added_mm=12.5),
        Observation("cam1", "calibration", "f001", np.array([3, 1]), rng.uniform(0, 1000, (2, 2))),
        Observation("cam0", "reconstruction", "r000", np.array([2]), rng.uniform(0, 1000, (1, 2)), stage_mm=-1.25),
    )
    return Dataset(
        root=root,
        rig_path=root / "rig.yaml",
        target=Target(type="charuco", squares=(8, 6), square_mm=15.0, marker_mm=11.0, dictionary="DICT_5X5_100"),
        interface=Interface(thickness_mm=25.4, index=1.4585, medium_index=1.333, distance_mm=80.0),
        cameras=cams,
        stacking=(Entry("stacking", "s0", {"cam0": images["a/c0_0.png"]}, added_mm=0.0),
                  Entry("stacking", "s0", {}, added_mm=12.5)),
        calibration=(
            Entry("calibration", "f000", {"cam0": images["a/c0_0.png"], "cam1": images["a/c1_0.png"]}),
            Entry("calibration", "f001", {}),
        ),
        reconstruction=(Entry("reconstruction", "r000", {"cam0": images["b/c0_1.png"]}, stage_mm=3.5),),
        observations=obs,
        observations_path=None,
    )


@pytest.mark.parametrize("rig_name", ["rig.yaml", "rig.json", "rig.yml"])
def test_rig_round_trip(tmp_path: Path, rig_name: str) -> None:
    ds = _rich_dataset(tmp_path)
    # written inside the source folder
    rig = save_rig(ds.root / rig_name, ds)
    first = load_dataset(rig)
    assert first.observations_path == ds.root / "observations.json"
    assert_records_equal(first.observations, ds.observations)
    for name in ("target", "interface", "cameras", "stacking", "calibration", "reconstruction"):
        assert_records_equal(getattr(first, name), getattr(ds, name))
    # load -> save elsewhere -> load: equal records, image paths still the same files
    second = load_dataset(save_rig(tmp_path / "copy" / rig_name, first))
    for name in ("target", "interface", "cameras", "stacking", "calibration", "reconstruction", "observations"):
        assert_records_equal(getattr(second, name), getattr(first, name))
    assert second.root == tmp_path / "copy"
    assert dump_rig(second)["calibration"][0]["images"]["cam0"] == "../src/a/c0_0.png"


def test_example_round_trip(tmp_path: Path) -> None:
    first = load_dataset(write_example(tmp_path / "ds"))
    second = load_dataset(save_rig(tmp_path / "ds" / "rig2.json", first))
    for name in ("target", "interface", "cameras", "stacking", "calibration", "reconstruction", "observations"):
        assert_records_equal(getattr(second, name), getattr(first, name))


def test_points3d_round_trip_yaml_and_json(tmp_path: Path) -> None:
    target = Target(type="points3d", points={3: (0.0, 0.0, 0.0), 10: (10.0, 0.0, 5.0), -1: (0.5, 1.5, 2.5)})
    ds = Dataset(tmp_path, tmp_path / "rig.yaml", target, Interface(10.0, 1.5), {"c": CameraSpec("c", (640, 480))})
    for name in ("rig.yaml", "rig.json"):
        loaded = load_dataset(save_rig(tmp_path / name, ds))
        assert loaded.target == target and loaded.observations is None


def test_observations_round_trip_full_precision(tmp_path: Path) -> None:
    pixels = np.array([[1021.123456789012, 733.1 + 1e-12], [0.1 + 0.2, 2047.4999999999998]])
    obs = (
        Observation("cam0", "stacking", "s1", np.array([4, 2]), pixels, added_mm=5.0),
        Observation("cam0", "calibration", "f000", np.array([4, 2]), pixels[::-1], stage_mm=1.0),
        Observation("cam1", "reconstruction", "r3", np.zeros(0, int), np.zeros((0, 2))),
    )
    path = tmp_path / "observations.json"
    save_observations(path, obs)
    raw = json.loads(path.read_text())["observations"]
    assert "pose" in raw[0] and "frame" not in raw[0] and "frame" in raw[1]
    assert "added_mm" not in raw[1] and "stage_mm" not in raw[0] and "stage_mm" not in raw[2]
    back = load_observations(path, Target("checkerboard", 1.0, (3, 2)), ["cam0", "cam1"])
    assert_records_equal(back, obs)
    assert back[0].pixels[0, 0] == 1021.123456789012  # bit-exact, not rounded


def test_points_round_trip(tmp_path: Path) -> None:
    frames = {
        "r000": {"stage_mm": 0.0, "ids": np.array([0, 1]), "xyz": np.array([[10.0, 0.1, 499.8], [20.0, 0.1, 1 / 3]]),
                 "ray_gap_mm": np.array([0.004, 0.006])},
        "r001": {"ids": [5], "xyz": [[1.0, 2.0, 3.0]], "ray_gap_mm": [0.0]},
    }
    path = tmp_path / "points.json"
    save_points(path, frames, "calibration.json")
    back = load_points(path)
    assert back["calibration"] == "calibration.json" and list(back["frames"]) == ["r000", "r001"]
    assert back["frames"]["r000"]["xyz"][1, 2] == 1 / 3
    assert back["frames"]["r001"]["stage_mm"] is None
    np.testing.assert_array_equal(back["frames"]["r000"]["ids"], [0, 1])
    example = tmp_path / "example_points.json"
    example.write_text(EXAMPLE_POINTS)
    assert load_points(example)["frames"]["r000"]["ray_gap_mm"].tolist() == [0.004, 0.006]


def test_read_structured_yaml_scientific_and_json(tmp_path: Path) -> None:
    (tmp_path / "a.yaml").write_text("x: 1e-3\ny: 2.5E+2\nz: '1e3'\n")
    assert read_structured(tmp_path / "a.yaml") == {"x": 0.001, "y": 250.0, "z": "1e3"}
    (tmp_path / "a.json").write_text('{"x": [1, 2.5]}')
    assert read_structured(tmp_path / "a.json") == {"x": [1, 2.5]}


# --------------------------------------------------------------------------- bad inputs


def _rig(**changes) -> dict:
    """The example rig as a mapping with dotted-key ``changes`` (value None deletes)."""
    rig = yaml.safe_load(EXAMPLE_RIG)
    for dotted, value in changes.items():
        keys = dotted.split("__")
        node = rig
        for k in keys[:-1]:
            node = node[int(k)] if isinstance(node, list) else node[k]
        last = int(keys[-1]) if isinstance(node, list) else keys[-1]
        if value is None:
            del node[last]
        else:
            node[last] = value
    return rig


def _obs(index: int = 0, **changes) -> str:
    data = json.loads(EXAMPLE_OBSERVATIONS)
    rec = data["observations"][index]
    for key, value in changes.items():
        if value is None:
            del rec[key]
        else:
            rec[key] = value
    return json.dumps(data)


BAD_RIGS = {
    "unknown format version": (_rig(format="ari-sfm/2"), "rig.yaml", "unsupported format 'ari-sfm/2'"),
    "missing format": (_rig(format=None), "rig.yaml", "missing key 'format'"),
    "missing key": (_rig(target__square_mm=None), "rig.yaml", "missing key 'target.square_mm'"),
    "missing interface": (_rig(interface=None), "rig.yaml", "missing key 'interface'"),
    "unknown target type": (_rig(target__type="hexagons"), "rig.yaml", "unknown target.type 'hexagons'"),
    "inner corners too few": (_rig(target__inner_corners=[11, 1]), "rig.yaml",
                              "target.inner_corners must be two integers >= 2"),
    "inner corners not ints": (_rig(target__inner_corners=[11.5, 8]), "rig.yaml",
                               "target.inner_corners must be two integers"),
    "square negative": (_rig(target__square_mm=-1), "rig.yaml", "target.square_mm must be > 0 (got -1)"),
    "square string": (_rig(target__square_mm="ten"), "rig.yaml", "target.square_mm must be a number (got 'ten')"),
    "thickness <= 0": (_rig(interface__thickness_mm=-5.0), "rig.yaml", "interface.thickness_mm must be > 0 (got -5.0)"),
    "thickness zero": (_rig(interface__thickness_mm=0), "rig.yaml", "interface.thickness_mm must be > 0 (got 0)"),
    "index < 1": (_rig(interface__index=0.9), "rig.yaml", "interface.index must be >= 1 (got 0.9)"),
    "medium index < 1": (_rig(interface__medium_index=0.5), "rig.yaml", "interface.medium_index must be >= 1"),
    "no cameras": (_rig(cameras={}), "rig.yaml", "cameras must declare at least one camera"),
    "bad image size": (_rig(cameras__cam0={"image_size": [0, 10]}), "rig.yaml",
                       "cameras.cam0.image_size must be two integers >= 1"),
    "bad dist": (_rig(cameras__cam0={"image_size": [10, 10], "dist": [0, 0, 0]}), "rig.yaml",
                 "cameras.cam0.dist must have 4, 5, 8, 12 or 14"),
    "bad K": (_rig(cameras__cam0={"image_size": [10, 10], "K": [[1, 0], [0, 1]]}), "rig.yaml",
              "cameras.cam0.K must have shape 3 x 3"),
    "bad focal": (_rig(cameras__cam0={"image_size": [10, 10], "focal_px": -3}), "rig.yaml",
                  "cameras.cam0.focal_px must be > 0"),
    "thickness 1e300": (_rig(interface__thickness_mm=1e300), "rig.yaml", "interface.thickness_mm must be <= 10000 mm"),
    "distance 1e9": (_rig(interface__distance_mm=1e9), "rig.yaml", "interface.distance_mm must be <= 10000 mm"),
    "index 50": (_rig(interface__index=50), "rig.yaml", "interface.index must be <= 5"),
    "square 1e20": (_rig(target__square_mm=1e20), "rig.yaml", "target.square_mm must be <= 10000 mm"),
    "image size 1e8": (_rig(cameras__cam0={"image_size": [100_000_000, 10]}), "rig.yaml",
                       "cameras.cam0.image_size must be <= 100000 px"),
    "focal 1e308": (_rig(cameras__cam0={"image_size": [10, 10], "focal_px": 1e308}), "rig.yaml",
                    "cameras.cam0.focal_px must be <= 1e+07 px"),
    "K fx 1e308": (_rig(cameras__cam0={"image_size": [10, 10], "K": [[1e308, 0, 5], [0, 1e3, 5], [0, 0, 1]]}),
                   "rig.yaml", "cameras.cam0.K focal length must be <= 1e+07 px"),
    "added_mm 1e300": (_rig(stacking__1__added_mm=1e300), "rig.yaml", "stacking[1].added_mm must be <= 10000 mm"),
    "stage_mm -1e300": (_rig(reconstruction__0__stage_mm=-1e300), "rig.yaml",
                        "|reconstruction[0].stage_mm| must be <= 10000 mm"),
    "camera not declared (images)": (
        _rig(calibration__0__images={"cam0": "calib/cam0_000.png", "cam7": "calib/cam1_000.png"}),
        "rig.yaml",
        "calibration[0] (frame f000): images name camera 'cam7', which is not declared",
    ),
    "image file missing": (
        _rig(calibration__0__images={"cam0": "calib/nope.png"}), "rig.yaml", "image of cam0 not found: calib/nope.png"
    ),
    "duplicate frame": (
        _rig(calibration=[{"frame": "f000", "images": {"cam0": "calib/cam0_000.png"}},
                          {"frame": "f000", "images": {"cam0": "calib/cam1_000.png"}}]),
        "rig.yaml",
        "calibration[1] (frame f000): frame 'f000' is already listed in calibration[0]",
    ),
    "duplicate stacking pose": (
        _rig(stacking__1__added_mm=0), "rig.yaml", "pose 's0' with added_mm 0 is already listed in stacking[0]"
    ),
    "stacking without added_mm": (_rig(stacking__0__added_mm=None), "rig.yaml", "missing key 'stacking[0].added_mm'"),
    "negative added_mm": (_rig(stacking__0__added_mm=-1), "rig.yaml", "stacking[0].added_mm must be >= 0"),
    "stage NaN": (_rig(reconstruction__0__stage_mm=float("nan")), "rig.yaml",
                  "reconstruction[0].stage_mm must be finite"),
    "entry without images and no observations": (
        _rig(calibration__0__images=None, observations=None), "rig.yaml", "calibration frame f000 has no images"
    ),
    "calibration not a list": (_rig(calibration={"frame": "f000"}), "rig.yaml", "calibration must be a list"),
    "charuco marker too big": (
        _rig(target={"type": "charuco", "squares": [5, 7], "square_mm": 10, "marker_mm": 10,
                     "dictionary": "DICT_4X4_50"}),
        "rig.yaml", "target.marker_mm must be < square_mm",
    ),
    "charuco unknown dictionary": (
        _rig(target={"type": "charuco", "squares": [5, 7], "square_mm": 10, "marker_mm": 7,
                     "dictionary": "DICT_9X9_1"}),
        "rig.yaml", "unknown target.dictionary 'DICT_9X9_1'",
    ),
    "charuco dictionary too small": (
        _rig(target={"type": "charuco", "squares": [20, 20], "square_mm": 10, "marker_mm": 7,
                     "dictionary": "DICT_4X4_50"}),
        "rig.yaml", "needs 200",
    ),
    "points3d bad xyz": (
        _rig(target={"type": "points3d", "points": {0: [0, 0], 1: [1, 2, 3]}}), "rig.yaml",
        "target.points[0] must have shape 3"
    ),
    "points3d bad id": (
        _rig(target={"type": "points3d", "points": {"a": [0, 0, 0]}}), "rig.yaml", "target.points: ids must be integers"
    ),
}


@pytest.mark.parametrize("case", list(BAD_RIGS), ids=list(BAD_RIGS))
def test_bad_rig(tmp_path: Path, case: str) -> None:
    rig, file_name, message = BAD_RIGS[case]
    folder = write_example(tmp_path / "ds", rig=yaml.safe_dump(rig))
    with pytest.raises(AriSfmError) as info:
        load_dataset(folder)
    assert info.value.path.endswith(file_name)
    assert message in info.value.message
    assert "\n" not in str(info.value)


BAD_OBSERVATIONS = {
    "unknown format version": (
        EXAMPLE_OBSERVATIONS.replace("ari-sfm-observations/1", "ari-sfm-observations/9"),
        "unsupported format 'ari-sfm-observations/9'",
    ),
    "missing key": (_obs(1, ids=None), "observation 1 (camera cam0, frame f000): missing key 'ids'"),
    "missing camera": (_obs(1, camera=None), "observation 1: missing key 'camera'"),
    "missing pose": (_obs(0, pose=None), "observation 0 (camera cam0): missing key 'pose'"),
    "ids out of range": (_obs(1, ids=[0, 88]), "observation 1 (camera cam0, frame f000): id 88 out of range"),
    "negative id": (_obs(1, ids=[-1, 0]), "id -1 out of range"),
    "duplicate ids": (_obs(1, ids=[1, 1]), "observation 1 (camera cam0, frame f000): duplicate id 1"),
    "NaN pixel": (
        EXAMPLE_OBSERVATIONS.replace("[1021.5, 733.0]", "[NaN, 733.0]"),
        "observation 1 (camera cam0, frame f000): pixels contain NaN",
    ),
    "null pixel": (_obs(1, pixels=[[1.0, None], [2.0, 3.0]]), "pixels contain null"),
    "string pixel": (_obs(1, pixels=[[1.0, "2"], [2.0, 3.0]]), "pixels must be numbers (got '2')"),
    "ragged pixels": (_obs(1, pixels=[[1.0, 2.0], [2.0]]), "pixels must be a regular list of numbers"),
    "pixels/ids length mismatch": (_obs(1, ids=[0, 1, 2]),
                                   "observation 1 (camera cam0, frame f000): 3 ids but 2 pixels"),
    "pixels wrong shape": (_obs(1, pixels=[[1.0, 2.0, 3.0], [1.0, 2.0, 3.0]]), "pixels must have shape N x 2"),
    "camera not declared": (_obs(2, camera="cam9"), "camera 'cam9' is not declared in the rig"),
    "unknown set": (_obs(2, set="test"), "set must be one of stacking, calibration, reconstruction"),
    "stacking without added_mm": (_obs(0, added_mm=None), "missing key 'added_mm'"),
    "added_mm outside stacking": (_obs(1, added_mm=3), "added_mm is only for stacking records"),
    "pixel outside image": (_obs(1, pixels=[[1.0, 2.0], [2449.0, 3.0]]),
                            "pixel (2449, 3) of id 1 is outside the 2448 x 2048 image"),
    "duplicate record": (
        json.dumps({"format": "ari-sfm-observations/1",
                    "observations": [json.loads(EXAMPLE_OBSERVATIONS)["observations"][1]] * 2}),
        "observation 1 (camera cam0, frame f000, set calibration) repeats observation 0",
    ),
    "malformed JSON": ('{"format": "ari-sfm-observations/1",\n "observations": [}', "malformed JSON at line 2"),
    "duplicate JSON key": ('{"format": "x", "format": "y"}', "duplicate key 'format'"),
    "not a mapping": ("[1, 2]", "the file must be a mapping"),
    "empty file": ("", "file is empty"),
}


@pytest.mark.parametrize("case", list(BAD_OBSERVATIONS), ids=list(BAD_OBSERVATIONS))
def test_bad_observations(tmp_path: Path, case: str) -> None:
    text, message = BAD_OBSERVATIONS[case]
    folder = write_example(tmp_path / "ds", observations=text)
    with pytest.raises(AriSfmError) as info:
        load_dataset(folder)
    assert info.value.path.endswith("observations.json")
    assert message in info.value.message
    assert "\n" not in str(info.value)


@pytest.mark.parametrize(
    "name, text, message",
    [
        ("rig.yaml", "format: ari-sfm/1\ntarget: [1, 2\n", "malformed YAML at line 3"),
        ("rig.yaml", "format: ari-sfm/1\n  bad: indent\n", "malformed YAML at line 2"),
        ("rig.yaml", "format: ari-sfm/1\nformat: ari-sfm/1\n",
         "malformed YAML at line 2, column 1: duplicate key 'format'"),
        ("rig.json", '{"format": "ari-sfm/1",\n "target": }', "malformed JSON at line 2, column 12"),
        ("rig.yaml", "", "file is empty"),
    ],
    ids=["yaml unclosed", "yaml indent", "yaml duplicate key", "json", "empty"],
)
def test_malformed_rig(tmp_path: Path, name: str, text: str, message: str) -> None:
    (tmp_path / name).write_text(text)
    with pytest.raises(AriSfmError) as info:
        load_dataset(tmp_path)
    assert info.value.path == str(tmp_path / name)
    assert message in info.value.message and "\n" not in str(info.value)


def test_missing_files(tmp_path: Path) -> None:
    with pytest.raises(AriSfmError, match="no such dataset folder"):
        load_dataset(tmp_path / "nowhere")
    with pytest.raises(AriSfmError, match="no rig.yaml, rig.yml or rig.json in this folder"):
        load_dataset(tmp_path)
    for loader in (load_observations, load_points, read_structured):
        with pytest.raises(AriSfmError) as info:
            loader(tmp_path / "missing.json")
        assert info.value.path == str(tmp_path / "missing.json") and info.value.message == "file not found"
    folder = write_example(tmp_path / "ds", observations=None)
    with pytest.raises(AriSfmError) as info:
        load_dataset(folder)
    assert info.value.path == str(folder / "observations.json") and info.value.message == "file not found"


def test_two_rig_files_are_ambiguous(tmp_path: Path) -> None:
    folder = write_example(tmp_path / "ds")
    (folder / "rig.json").write_text(json.dumps(yaml.safe_load(EXAMPLE_RIG)))
    with pytest.raises(AriSfmError, match="both rig.yaml and rig.json"):
        load_dataset(folder)


def test_observations_file_without_target_or_cameras(tmp_path: Path) -> None:
    path = tmp_path / "o.json"
    path.write_text(_obs(1, ids=[0, 500]))
    assert load_observations(path)[1].ids.tolist() == [0, 500]  # no target: any ids
    with pytest.raises(AriSfmError, match="id 500 out of range"):
        load_observations(path, Target("checkerboard", 1.0, (11, 8)))
    with pytest.raises(AriSfmError, match="camera 'cam0' is not declared"):
        load_observations(path, camera_names=["cam1"])


@pytest.mark.parametrize(
    "frame, message",
    [
        ({"ids": [0, 1], "xyz": [[0, 0, 0]], "ray_gap_mm": [0, 0]}, "frames.r000: 2 ids, 1 xyz and 2 ray_gap_mm"),
        ({"ids": [0, 0], "xyz": [[0, 0, 0]] * 2, "ray_gap_mm": [0, 0]}, "frames.r000: duplicate id 0"),
        ({"ids": [0], "xyz": [[0, float("nan"), 0]], "ray_gap_mm": [0]}, "frames.r000.xyz contain NaN"),
        ({"ids": [0], "xyz": [[0, 0, 0]], "ray_gap_mm": [-1]}, "frames.r000.ray_gap_mm must be >= 0"),
        ({"xyz": [[0, 0, 0]], "ray_gap_mm": [0]}, "missing key 'frames.r000.ids'"),
    ],
    ids=["length", "duplicate ids", "nan", "negative gap", "missing ids"],
)
def test_bad_points(tmp_path: Path, frame: dict, message: str) -> None:
    path = tmp_path / "points.json"
    path.write_text(json.dumps({"format": "ari-sfm-points/1", "calibration": "c.json", "frames": {"r000": frame}}))
    with pytest.raises(AriSfmError) as info:
        load_points(path)
    assert info.value.path == str(path) and message in info.value.message
    # the writer refuses the same frame and writes nothing
    with pytest.raises(AriSfmError):
        save_points(tmp_path / "out.json", {"r000": frame}, "c.json")
    assert not (tmp_path / "out.json").exists()


def test_bad_points_format(tmp_path: Path) -> None:
    path = tmp_path / "points.json"
    path.write_text(EXAMPLE_POINTS.replace("ari-sfm-points/1", "ari-sfm-points/2"))
    with pytest.raises(AriSfmError, match="unsupported format 'ari-sfm-points/2'"):
        load_points(path)


def test_save_observations_refuses_bad_records(tmp_path: Path) -> None:
    path = tmp_path / "observations.json"
    good = Observation("cam0", "calibration", "f0", np.array([0]), np.array([[1.0, 2.0]]))
    save_observations(path, [good])
    before = path.read_text()
    bad = Observation("cam0", "calibration", "f1", np.array([0]), np.array([[np.nan, 2.0]]))
    with pytest.raises(AriSfmError, match=r"observation 1 \(camera cam0, frame f1\): pixels contain NaN"):
        save_observations(path, [good, bad])
    assert path.read_text() == before and os.listdir(tmp_path) == ["observations.json"]


# --------------------------------------------------------------------------- atomic writes


def test_atomic_json_failure_keeps_old_file(tmp_path: Path) -> None:
    path = tmp_path / "out.json"
    write_json_atomic(path, {"a": np.arange(3), "b": np.float32(0.5), "k": np.eye(2)})
    before = path.read_text()
    assert json.loads(before) == {"a": [0, 1, 2], "b": 0.5, "k": [[1.0, 0.0], [0.0, 1.0]]}
    with pytest.raises(TypeError):
        write_json_atomic(path, {"a": [1, 2, {"deep": object()}]})
    with pytest.raises(AriSfmError) as info:
        write_json_atomic(path, {"a": {"b": [1.0, float("nan")]}})
    assert info.value.path == str(path) and "a.b[1]" in info.value.message
    assert path.read_text() == before and os.listdir(tmp_path) == ["out.json"]


def test_atomic_text_failure_midway_removes_temp(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / "out.txt"
    write_text_atomic(path, "old\n")

    def boom(fd: int) -> None:
        raise OSError(5, "Input/output error")

    monkeypatch.setattr(os, "fsync", boom)
    with pytest.raises(AriSfmError, match="cannot write file: Input/output error"):
        write_text_atomic(path, "new\n" * 1000)
    assert path.read_text() == "old\n" and os.listdir(tmp_path) == ["out.txt"]


def test_atomic_write_creates_folder_and_replaces(tmp_path: Path) -> None:
    path = tmp_path / "a" / "b" / "x.txt"
    write_text_atomic(path, "1")
    write_text_atomic(path, "2")
    assert path.read_text() == "2" and os.listdir(path.parent) == ["x.txt"]


def test_json_text_in_rig_yaml_loads(tmp_path: Path) -> None:
    """JSON is valid YAML: a rig.yaml holding JSON text loads the same."""
    folder = write_example(tmp_path / "ds", rig=json.dumps(yaml.safe_load(EXAMPLE_RIG), indent=2))
    assert load_dataset(folder).target.inner_corners == (11, 8)


def test_random_corruptions_raise_only_ari_sfm_error(tmp_path: Path) -> None:
    """Replace random values of the example with values of wrong types: only AriSfmError escapes."""
    import copy
    import random

    def paths(obj, prefix=()):
        yield prefix
        items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
        for k, v in items:
            yield from paths(v, prefix + (k,))

    junk = [None, True, 0, -1, 1.5, float("nan"), "", "x", [], [1], [[1, 2], [3]], {}, {"a": 1}, [None], 10**30]
    rng = random.Random(0)
    rig0, obs0 = yaml.safe_load(EXAMPLE_RIG), json.loads(EXAMPLE_OBSERVATIONS)
    write_example(tmp_path)
    for _ in range(150):
        rig, obs = copy.deepcopy(rig0), copy.deepcopy(obs0)
        doc = rng.choice([rig, obs])
        where = rng.choice([p for p in paths(doc) if p])
        node = doc
        for k in where[:-1]:
            node = node[k]
        node[where[-1]] = copy.deepcopy(rng.choice(junk))
        (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
        (tmp_path / "observations.json").write_text(json.dumps(obs))
        try:
            load_dataset(tmp_path)
        except AriSfmError as exc:
            assert "\n" not in str(exc) and exc.path is not None


def test_unknown_keys_load_with_a_warning(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    """New keys are allowed (the format may grow) but a typo must not pass silently."""
    rig = _rig(interface__medium_indx=1.333, lab="tank 2")
    folder = write_example(tmp_path / "ds", rig=yaml.safe_dump(rig), observations=_obs(1, detector="opencv"))
    with caplog.at_level("WARNING", logger="ari_sfm.io"):
        ds = load_dataset(folder)
    assert ds.interface.medium_index == 1.0
    text = caplog.text
    assert "'interface.medium_indx'" in text and "'lab'" in text and "'observations[].detector'" in text


# --------------------------------------------------------------------------- manual_points (1.3)

MANUAL = {"cam0": {2: [1009.0, 608.0], 3: [979.0, 335.0], 71: [246.0, 620.0], 73: [235.0, 344.0]},
          "cam1": {2: [1002.5, 609.25], 3: [1013.0, 335.0], 71: [261.0, 620.0], 73: [285.0, 355.0], 40: [600.0, 500.0]}}


def _body_rig(tmp_path: Path, manual=MANUAL, target=None, extra_entry=None) -> Path:
    """A points3d rig with one calibration entry (images of cam0, cam1) holding ``manual``."""
    (tmp_path / "cal").mkdir(parents=True, exist_ok=True)
    for cam in ("cam0", "cam1"):
        (tmp_path / "cal" / f"{cam}.tif").write_bytes(b"not read when loading")
    points = {i: [float(i), 0.5 * i, float(i % 3)] for i in range(1, 74)}
    entry = {"frame": "f000", "images": {"cam0": "cal/cam0.tif", "cam1": "cal/cam1.tif"}, "manual_points": manual}
    if extra_entry:
        entry.update(extra_entry)
    rig = {"format": "ari-sfm/1", "target": target or {"type": "points3d", "points": points},
           "interface": {"thickness_mm": 6.0, "index": 1.49, "medium_index": 1.333},
           "cameras": {"cam0": {"image_size": [1280, 1024]}, "cam1": {"image_size": [1280, 1024]}},
           "calibration": [entry]}
    (tmp_path / "rig.yaml").write_text(yaml.safe_dump(rig))
    return tmp_path / "rig.yaml"


@pytest.mark.parametrize("rig_name", ["rig.yaml", "rig.json"])
def test_manual_points_round_trip(tmp_path: Path, rig_name: str) -> None:
    """manual_points load as {camera: {id: (u, v)}} OpenCV pixels and save_rig writes them back unchanged."""
    first = load_dataset(_body_rig(tmp_path / "src"))
    clicks = first.calibration[0].manual_points
    assert list(clicks) == ["cam0", "cam1"] and clicks["cam1"][2] == (1002.5, 609.25) and len(clicks["cam1"]) == 5
    second = load_dataset(save_rig(tmp_path / "copy" / rig_name, first))
    assert_records_equal(second.calibration, first.calibration)
    assert dump_rig(second)["calibration"][0]["manual_points"]["cam0"][71] == [246.0, 620.0]


def test_points3d_diameter_round_trip(tmp_path: Path) -> None:
    points = {1: [0, 0, 0], 2: [10, 0, 0], 3: [0, 10, 5]}
    first = load_dataset(_body_rig(tmp_path / "src", manual=None, target={"type": "points3d", "points": points,
                                                                           "diameter_mm": 1.5}))
    assert first.target.diameter_mm == 1.5
    assert load_dataset(save_rig(tmp_path / "copy" / "rig.yaml", first)).target == first.target


@pytest.mark.parametrize("manual, message", [
    ({"cam7": MANUAL["cam0"]}, "calibration[0].manual_points.cam7: camera 'cam7' is not declared in cameras"),
    ({"cam0": {**MANUAL["cam0"], 99: [1.0, 2.0]}},
     "calibration[0].manual_points.cam0: id 99 is not a point of the target"),
    ({"cam0": {**MANUAL["cam0"], 5: [float("nan"), 2.0]}}, "calibration[0].manual_points.cam0[5] contain NaN"),
    ({"cam0": {**MANUAL["cam0"], 5: [float("inf"), 2.0]}}, "calibration[0].manual_points.cam0[5] contain infinity"),
    ({"cam0": {**MANUAL["cam0"], 5: [1280.0, 2.0]}}, "calibration[0].manual_points.cam0[5]: pixel (1280, 2) is outside "
                                                     "the 1280 x 1024 image"),
    ({"cam0": {**MANUAL["cam0"], 5: [3.0, -0.6]}}, "pixel (3, -0.6) is outside the 1280 x 1024 image"),
    ({"cam0": {2: [1.0, 2.0], 3: [3.0, 4.0], 71: [5.0, 6.0]}}, "calibration[0].manual_points.cam0: 3 clicked points, "
                                                              "need >= 4"),
    ({"cam0": {**MANUAL["cam0"], 5: [1.0]}}, "calibration[0].manual_points.cam0[5] must have shape 2 (got 1)"),
    ({"cam0": [[1, 2], [3, 4]]}, "calibration[0].manual_points.cam0 must be a mapping"),
    ([1, 2], "calibration[0].manual_points must be a mapping"),
    ({"cam0": {"two": [1.0, 2.0]}}, "calibration[0].manual_points.cam0: ids must be integers (got 'two')"),
])
def test_bad_manual_points_are_one_line_naming_the_key(tmp_path: Path, manual, message: str) -> None:
    with pytest.raises(AriSfmError) as info:
        load_dataset(_body_rig(tmp_path, manual))
    assert info.value.path.endswith("rig.yaml") and message in info.value.message, info.value.message
    assert "\n" not in str(info.value)


def test_manual_points_only_for_a_body_in_calibration_entries(tmp_path: Path) -> None:
    board = {"type": "checkerboard", "inner_corners": [11, 8], "square_mm": 10.0}
    with pytest.raises(AriSfmError, match=r"calibration\[0\].manual_points: clicked points identify a 3D body"):
        load_dataset(_body_rig(tmp_path / "a", target=board))
    rig = _body_rig(tmp_path / "b")
    data = yaml.safe_load(rig.read_text())
    data["reconstruction"] = [{**data["calibration"][0], "frame": "r000"}]
    rig.write_text(yaml.safe_dump(data))
    with pytest.raises(AriSfmError, match=r"reconstruction\[0\].manual_points: clicked points are for calibration"):
        load_dataset(rig)
