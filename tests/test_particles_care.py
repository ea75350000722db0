"""Input care of `detect-particles` and `particles`: what cannot be right is refused in one line (frames
beyond the images, images of another size or beyond the stated size, pixels outside the image, a model
without the window, an empty table), what is suspicious is said (repeated rows, a low matched fraction),
a changed image is detected again on a re-run, and an interrupted or full-disk write leaves no table."""
from __future__ import annotations

import errno
import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pyarrow as pa
import pyarrow.parquet as pq
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.simulate.particles import ParticleSimOptions, simulate_particle_experiment, write_particle_experiment


@pytest.fixture(scope="module")
def sim(tmp_path_factory):
    """300 particles, 4 frames, 4 cameras, no images (the tester's `simulate particles --particles 300
    --frames 4`), and another experiment of the same rig layout (another seed)."""
    root = tmp_path_factory.mktemp("care")
    write_particle_experiment(simulate_particle_experiment(ParticleSimOptions(particles_per_frame=300, num_frames=4,
                                                                              seed=3)), root / "a", render_frames=0)
    write_particle_experiment(simulate_particle_experiment(ParticleSimOptions(particles_per_frame=300, num_frames=4,
                                                                              seed=8)), root / "b", render_frames=0)
    return root


@pytest.fixture(scope="module")
def small_images(tmp_path_factory):
    """A simulated rig's rig.yaml with two cameras whose images are 320 x 256 px (fast to detect): two
    frames of 40 rendered Gaussian particle images each."""
    from ari_sfm.simulate.particle_images import render_particle_image

    root = tmp_path_factory.mktemp("care_images")
    exp = simulate_particle_experiment(ParticleSimOptions(num_cameras=2, particles_per_frame=10, num_frames=2,
                                                          drift_cameras=(), seed=4))
    write_particle_experiment(exp, root / "sim", render_frames=0)
    folder = root / "sim" / "experiment"
    rig = (folder / "rig.yaml").read_text().replace("- 2448\n    - 2048", "- 320\n    - 256")
    rig = rig.replace("particles:\n", "particles:\n  images:\n    cam0: images/cam0/{frame:05d}.png\n"
                                      "    cam1: images/cam1/{frame:05d}.png\n  frames:\n  - 0\n  - 1\n")
    (folder / "rig.yaml").write_text(rig)
    rng = np.random.default_rng(4)
    for cam in ("cam0", "cam1"):
        (folder / "images" / cam).mkdir(parents=True)
        for f in range(2):
            uv = rng.uniform((8, 8), (312, 248), (40, 2))
            image = render_particle_image(uv, (320, 256), 3.0, rng=rng)
            cv2.imwrite(str(folder / "images" / cam / f"{f:05d}.png"), image)
    return folder


def _copy(folder: Path, dst: Path) -> Path:
    shutil.copytree(folder, dst)
    return dst


def _run(args) -> object:
    return CliRunner().invoke(main, [str(a) for a in args])


def _error(args) -> str:
    """The one error line of a command that fails (exit 1), besides its progress bar."""
    r = _run(args)
    lines = [line for line in r.output.replace("\r", "\n").splitlines()
             if line.strip() and not line.startswith(("detecting:", "matching:"))]
    assert r.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: "), r.output
    return lines[0]


def _particles(sim: Path, out: Path, *extra) -> object:
    return _run(["particles", sim / "a" / "experiment", "--calibration", sim / "a" / "truth" / "rig_b.json", "-o", out,
                 "--workers", "0", *extra])


# --------------------------------------------------------------------------- detect-particles: frames, sizes


def test_frames_beyond_the_images_are_refused_at_once(small_images, tmp_path):
    """frames: [0, 1000000000] (the images end at 1): refused naming the last frame's missing image, before
    any per-frame work (detect-particles was killed at 22.7 GB building them); a missing image inside the
    range stops the run at its partition, naming it, and keeps the partitions before it."""
    folder = _copy(small_images, tmp_path / "exp")
    rig = folder / "rig.yaml"
    rig.write_text(rig.read_text().replace("frames:\n  - 0\n  - 1", "frames:\n  - 0\n  - 1000000000"))
    line = _error(["detect-particles", folder, "-o", tmp_path / "d1", "--workers", "0"])
    assert "frame 1000000000: no such image" in line and "01000000000.png" not in line
    assert str(folder / "images" / "cam0" / "1000000000.png") in line
    rig.write_text(rig.read_text().replace("- 1000000000", "- 2"))
    shutil.copy(folder / "images" / "cam0" / "00000.png", folder / "images" / "cam0" / "00002.png")
    shutil.copy(folder / "images" / "cam1" / "00000.png", folder / "images" / "cam1" / "00002.png")
    (folder / "images" / "cam1" / "00001.png").unlink()
    line = _error(["detect-particles", folder, "-o", tmp_path / "d2", "--workers", "0", "--frames-per-partition", "1"])
    assert "frame 1: no such image" in line and "cam1" in line
    assert [p.name for p in (tmp_path / "d2" / "parts").glob("*.parquet")] == ["frames_00000-00000.parquet"]
    assert not (tmp_path / "d2" / "particles.parquet").exists()


@pytest.mark.parametrize("size", [(1224, 1024), (1000, 800), (1, 1)])
def test_an_image_of_another_size_is_refused(small_images, tmp_path, size):
    """One image of another size among the rig's 320 x 256: refused naming the file and both sizes."""
    folder = _copy(small_images, tmp_path / "exp")
    path = folder / "images" / "cam1" / "00001.png"
    cv2.imwrite(str(path), np.zeros((size[1], size[0]), np.uint8))
    line = _error(["detect-particles", folder, "-o", tmp_path / "d", "--workers", "0"])
    assert line.startswith(f"error: {path}: the image is {size[0]} x {size[1]} px, but cam1's images are 320 x 256")
    assert not (tmp_path / "d" / "particles.parquet").exists()


def test_an_image_of_another_size_is_refused_before_it_is_decoded(small_images, tmp_path, monkeypatch):
    """A 16000 x 16000 image (4.7 GB in the detector) is refused on its header: never decoded (a 6000 x 5000
    one too, below Pillow's decompression-bomb limit)."""
    from ari_sfm.particles import detect

    folder = _copy(small_images, tmp_path / "exp")
    path = folder / "images" / "cam0" / "00000.png"
    cv2.imwrite(str(path), np.zeros((16000, 16000), np.uint8))
    decoded = []
    real = cv2.imread
    monkeypatch.setattr(cv2, "imread", lambda p, *a: decoded.append(p) or real(p, *a))
    with pytest.raises(detect.PartitionError, match="the image is more than 179 MP, but cam0's images are 320 x 256"):
        detect.read_image(path, (320, 256), "cam0")
    cv2.imwrite(str(path), np.zeros((5000, 6000), np.uint8))
    with pytest.raises(detect.PartitionError, match="the image is 6000 x 5000 px, but cam0's images are 320 x 256"):
        detect.read_image(path, (320, 256), "cam0")
    assert decoded == []


def test_images_beyond_the_stated_size_are_refused(small_images, tmp_path):
    """A rig whose images are larger than MAX_IMAGE_PIXELS (40 MP, ~1.6 GB in the detector): one line."""
    folder = _copy(small_images, tmp_path / "exp")
    rig = folder / "rig.yaml"
    rig.write_text(rig.read_text().replace("- 320\n    - 256", "- 16000\n    - 16000", 1))
    line = _error(["detect-particles", folder, "-o", tmp_path / "d", "--workers", "0"])
    assert "cameras.cam0.image_size: 16000 x 16000 px (256 MP) is more than detect-particles handles (40 MP" in line
    assert not (tmp_path / "d").exists()


def test_a_changed_image_is_detected_again(small_images, tmp_path):
    """A re-run into the same -o after an image changed detects its partition again (the partition's key
    holds its images' sizes and times); the other partition is reused as it is."""
    folder = _copy(small_images, tmp_path / "exp")
    out = tmp_path / "det"
    args = ["detect-particles", folder, "-o", out, "--workers", "0", "--frames-per-partition", "1"]
    assert _run(args).exit_code == 0
    before = pq.read_table(out / "particles.parquet")
    frame, camera = before.column("frame").to_numpy(), before.column("camera").to_numpy(zero_copy_only=False)
    assert ((frame == 1) & (camera == "cam1")).sum() > 20
    kept = out / "parts" / "frames_00000-00000.parquet"
    stamp = kept.stat().st_mtime_ns
    cv2.imwrite(str(folder / "images" / "cam1" / "00001.png"), np.zeros((256, 320), np.uint8))  # now blank
    r = _run(args)
    assert r.exit_code == 0, r.output
    after = pq.read_table(out / "particles.parquet")
    frame, camera = after.column("frame").to_numpy(), after.column("camera").to_numpy(zero_copy_only=False)
    assert ((frame == 1) & (camera == "cam1")).sum() == 0
    assert before.filter(pa.compute.equal(before.column("frame"), 0)).equals(
        after.filter(pa.compute.equal(after.column("frame"), 0)))
    assert kept.stat().st_mtime_ns == stamp  # reused, not detected again


def test_blank_images_are_an_error_not_an_empty_success(small_images, tmp_path):
    """An experiment whose images hold no particle: one error line (exit 1) and no particles.parquet; a
    camera blank in every frame: a warning, in detect-particles.json too."""
    folder = _copy(small_images, tmp_path / "exp")
    for path in (folder / "images" / "cam1").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((256, 320), np.uint8))
    r = _run(["detect-particles", folder, "-o", tmp_path / "d1", "--workers", "0"])
    assert r.exit_code == 0, r.output
    summary = json.loads((tmp_path / "d1" / "detect-particles.json").read_text())
    assert summary["per_camera"]["cam1"] == 0 and summary["per_camera"]["cam0"] > 0
    assert summary["warnings"] and summary["warnings"][0].startswith("cam1: no particle image found")
    for path in (folder / "images" / "cam0").glob("*.png"):
        cv2.imwrite(str(path), np.zeros((256, 320), np.uint8))
    line = _error(["detect-particles", folder, "-o", tmp_path / "d1", "--workers", "0"])  # the same -o
    assert "no particle image found in any of the 4 images (frames 0..1)" in line
    assert not (tmp_path / "d1" / "particles.parquet").exists()  # the earlier run's is not left as this one's
    assert not (tmp_path / "d1" / "detect-particles.json").exists()


# --------------------------------------------------------------------------- particles: the table, the model


def _table(sim: Path) -> pa.Table:
    return pq.read_table(sim / "a" / "experiment" / "particles.parquet")


def _with_table(sim: Path, tmp_path: Path, table: pa.Table) -> Path:
    path = tmp_path / "detections.parquet"
    pq.write_table(table, path)
    return path


def test_repeated_rows_are_counted_once(sim, tmp_path):
    """The table appended to itself (2400 rows of each particle image's pair): the same particles as the
    table once (not twice as many), the repeats said and recorded."""
    once = _particles(sim, tmp_path / "once")
    assert once.exit_code == 0, once.output
    table = _table(sim)
    twice = _with_table(sim, tmp_path, pa.concat_tables([table, table]))
    r = _particles(sim, tmp_path / "twice", "--detections", twice)
    assert r.exit_code == 0, r.output
    a = json.loads((tmp_path / "once" / "particles3d.json").read_text())
    b = json.loads((tmp_path / "twice" / "particles3d.json").read_text())
    assert b["particles"] == a["particles"] >= 0.95 * 1200
    assert b["repeated_rows"] == table.num_rows and a["repeated_rows"] == 0
    assert b["detections_total"] == a["detections_total"] == table.num_rows
    rows = pq.read_table(tmp_path / "twice" / "particles3d.parquet").column("row_cam0").to_numpy()
    assert rows.max() < table.num_rows  # the first of each pair


def test_pixels_outside_the_image_are_refused(sim, tmp_path):
    table = _table(sim)
    u = table.column("u").to_numpy().copy()
    u[10] += 5000.0
    path = _with_table(sim, tmp_path, table.set_column(table.column_names.index("u"), "u", pa.array(u)))
    camera = table.column("camera")[10].as_py()
    line = _error(["particles", sim / "a" / "experiment", "--calibration", sim / "a" / "truth" / "rig_b.json",
                   "-o", tmp_path / "o", "--workers", "0", "--detections", path])
    assert line.startswith(f"error: {path}: row 10: camera {camera}: pixel (")
    assert "outside its 2448 x 2048 image" in line


def test_a_pinhole_calibration_is_refused(sim, tmp_path):
    """A pinhole calibration ignores the window: particles through it would be wrong, refused."""
    cal = json.loads((sim / "a" / "truth" / "rig_b.json").read_text())
    cal["model"] = "pinhole"
    path = tmp_path / "pinhole.json"
    path.write_text(json.dumps(cal))
    line = _error(["particles", sim / "a" / "experiment", "--calibration", path, "-o", tmp_path / "o",
                   "--workers", "0"])
    assert line == (f"error: {path}: model pinhole ignores the window (a plain camera): particles need a model "
                    "with rays through the window (exact, ari, rt)")
    from ari_sfm.io import load_calibration
    from ari_sfm.particles.match import match_frame

    with pytest.raises(ValueError, match="model pinhole has no rays through the window"):  # the API too
        match_frame(load_calibration(path), {"cam0": np.zeros((1, 2)), "cam1": np.zeros((1, 2))}, 0.5,
                    depth_range_mm=(300.0, 500.0), min_cameras=2)


def test_an_empty_table_is_an_error(sim, tmp_path):
    path = _with_table(sim, tmp_path, _table(sim).slice(0, 0))
    line = _error(["particles", sim / "a" / "experiment", "--calibration", sim / "a" / "truth" / "rig_b.json",
                   "-o", tmp_path / "o", "--workers", "0", "--detections", path])
    assert line.startswith(f"error: {path}: holds no particle image (0 rows)")
    assert not (tmp_path / "o" / "particles3d.parquet").exists()


def test_another_experiments_detections_are_said_not_to_fit(sim, tmp_path, caplog):
    """Another experiment's detections through this rig's calibration match a few chance images: said in a
    warning and in particles3d.json (exit 0: the result is written, and a drifted rig's is the start of
    self-calibration); the summary line counts detections, not particles found."""
    good = _particles(sim, tmp_path / "good")
    assert good.exit_code == 0 and not [r for r in caplog.records if r.levelname == "WARNING"]
    assert "particles in 4 frames, triangulated from" in good.output and "of the 4800 detections" in good.output
    r = _particles(sim, tmp_path / "other", "--detections", sim / "b" / "experiment" / "particles.parquet")
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "other" / "particles3d.json").read_text())
    assert s["matched_fraction"] < 0.05 and len(s["warnings"]) == 1
    assert "particle images (detections) were matched into particles: the calibration does not fit these " \
           "images; run ari-sfm self-calibrate" in s["warnings"][0]
    assert [r.getMessage() for r in caplog.records if r.levelname == "WARNING"] == s["warnings"]  # and logged
    # one camera's detections from the other experiment: that camera is named
    a, b = _table(sim), pq.read_table(sim / "b" / "experiment" / "particles.parquet")
    cam = pa.compute.equal
    mixed = pa.concat_tables([a.filter(pa.compute.invert(cam(a.column("camera"), "cam2"))),
                              b.filter(cam(b.column("camera"), "cam2"))])
    r = _particles(sim, tmp_path / "mixed", "--detections", _with_table(sim, tmp_path, mixed))
    assert r.exit_code == 0, r.output
    s = json.loads((tmp_path / "mixed" / "particles3d.json").read_text())
    assert s["matched_fraction"] > 0.5 and s["matched_fraction_per_camera"]["cam2"] < 0.05
    assert len(s["warnings"]) == 1 and s["warnings"][0].startswith("cam2: only ")


# --------------------------------------------------------------------------- partial output


def test_an_interrupted_or_full_disk_merge_leaves_no_table(sim, tmp_path, monkeypatch):
    """Ctrl-C or a full disk while the partitions are written as the final table: no particles3d.parquet,
    no temporary file; the same command then completes from the partitions."""
    calls = []
    real = pq.ParquetWriter.write_table

    def interrupted(self, table, *a, **k):  # at the final table's second partition
        calls.extend(["particles3d" in str(self.where)])
        if sum(calls) == 2:
            raise KeyboardInterrupt
        return real(self, table, *a, **k)

    monkeypatch.setattr(pq.ParquetWriter, "write_table", interrupted)
    out = tmp_path / "p3d"
    r = _particles(sim, out, "--frames-per-partition", "1")
    assert r.exit_code == 130 and r.output.strip().splitlines()[-1] == "interrupted", r.output
    assert not (out / "particles3d.parquet").exists() and not list(out.rglob("*.tmp"))
    assert len(list((out / "parts").glob("*.parquet"))) == 4

    def full(self, table, *a, **k):
        if "particles3d" in str(self.where):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, table, *a, **k)

    monkeypatch.setattr(pq.ParquetWriter, "write_table", full)
    line = _error(["particles", sim / "a" / "experiment", "--calibration", sim / "a" / "truth" / "rig_b.json",
                   "-o", out, "--workers", "0", "--frames-per-partition", "1"])
    assert line == f"error: {out / 'particles3d.parquet'}: cannot write file: No space left on device"
    assert not (out / "particles3d.parquet").exists() and not list(out.rglob("*.tmp"))
    monkeypatch.setattr(pq.ParquetWriter, "write_table", real)
    r = _particles(sim, out, "--frames-per-partition", "1")
    assert r.exit_code == 0 and "4 partitions resumed" in r.output, r.output
    assert pq.read_table(out / "particles3d.parquet").num_rows >= 0.95 * 1200


def test_detect_particles_on_a_full_disk_leaves_no_table(small_images, tmp_path, monkeypatch):
    import ari_sfm.io.atomic as atomic

    out = tmp_path / "det"
    real = atomic.os.replace

    def replace(src, dst):  # the partitions and run.json are written; the final table is not
        if Path(dst).name in ("particles.parquet", "detect-particles.json"):
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(src, dst)

    monkeypatch.setattr(atomic.os, "replace", replace)
    line = _error(["detect-particles", small_images, "-o", out, "--workers", "0"])
    assert line == f"error: {out / 'particles.parquet'}: cannot write file: No space left on device"
    assert not (out / "particles.parquet").exists() and not list(out.rglob("*.tmp"))
