"""`ari-sfm run` end to end on a simulated binocular rig with stage frames, and its report.html.

The report is checked twice: its content (tables hold the calibration's and
the metrics' numbers, every figure is a decodable embedded PNG, nothing is
fetched from elsewhere), and as a person would see it, rendered by headless
Chromium (screenshot not blank, every <img> loaded).
"""
from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.calibration import load_calibration
from ari_sfm.cli import main
from ari_sfm.report import calibration_rows, markdown_tables, write_report
from ari_sfm.simulate import simulate

ROOT = Path(__file__).resolve().parents[1]
IMG = re.compile(r'<img alt="([^"]*)" src="data:image/png;base64,([A-Za-z0-9+/=]+)">')


@pytest.fixture(scope="module")
def binocular(tmp_path_factory):
    """A simulated binocular rig (sigma 0.05 px) with 11 stage frames, run with the exact model."""
    base = tmp_path_factory.mktemp("report")
    ds, truth = simulate("binocular", base / "sim", seed=0, images=False)
    out = base / "out"
    r = CliRunner().invoke(main, ["run", str(ds), "-o", str(out), "--model", "exact", "--truth", str(truth)])
    assert r.exit_code == 0, r.output
    return ds, truth, out, r.output


def _images(text: str) -> dict[str, np.ndarray]:
    return {alt: mpimg.imread(io.BytesIO(base64.b64decode(data)), format="png") for alt, data in IMG.findall(text)}


def test_run_calibrates_reconstructs_and_reports(binocular):
    ds, truth, out, output = binocular
    for name in ("calibration.json", "points.json", "metrics.json", "run.json", "report.html", "clouds/all.ply"):
        assert (out / name).exists(), name
    assert f"report: {out / 'report.html'}" in output
    run = json.loads((out / "run.json").read_text())
    assert run["format"] == "ari-sfm-run/1" and Path(run["dataset"]) == ds.resolve() and run["model"] == "exact"
    assert run["reconstruction"] == {"frames": 11, "points": 968} and run["reconstruction_skipped"] is None
    m = json.loads((out / "metrics.json").read_text())  # issue 6, item 6
    assert m["truth"]["aligned"]["rms_mm"] < 0.05
    assert m["flatness_mm"]["rmse"] < 0.03
    assert m["stage"]["plane_distance_error_mm"]["max"] < 0.02
    assert m["inter_corner_mm"]["rmse"] < 0.02
    assert not list(out.glob(".*"))  # no temporary files left


def test_report_tables_hold_the_calibrations_numbers(binocular):
    _, _, out, _ = binocular
    text = (out / "report.html").read_text()
    cal = load_calibration(out / "calibration.json")
    unc = cal.uncertainty
    for name, cam in cal.cameras.items():
        for key, value in zip(("fx", "fy", "cx", "cy"), cam.params[:4]):
            assert f">{value:.4f}<" in text, (name, key)
            assert f">{unc.cameras[name].intrinsics[key]:.4f}<" in text, (name, key)  # its standard deviation
        assert f">{cam.expansion_center_px[0]:.4f}<" in text and f">{cam.expansion_center_std_px[1]:.4f}<" in text
    assert f">{unc.normal_deg:.4f}<" in text
    assert f">{unc.cameras['cam1'].translation_mm:.4f}<" in text
    rows = calibration_rows(cal)
    assert {r[1] for r in rows} >= {"fx (px)", "fy (px)", "cx (px)", "cy (px)", "expansion centre u (px)"}
    baseline = next(r[2] for r in rows if r[1].startswith("baseline"))
    centres = [c.cam_from_world.inverse().t for c in cal.cameras.values()]
    assert baseline == pytest.approx(np.linalg.norm(centres[1] - centres[0]), rel=1e-12)
    m = json.loads((out / "metrics.json").read_text())
    for key in ("mae", "rmse", "max"):
        assert f">{m['flatness_mm'][key]:.4f}<" in text and f">{m['inter_corner_mm'][key]:.4f}<" in text
    assert f">{m['truth']['aligned']['rms_mm']:.4f}<" in text


def test_report_embeds_every_figure_and_fetches_nothing(binocular):
    _, _, out, _ = binocular
    text = (out / "report.html").read_text()
    images = _images(text)
    assert set(images) == {"residual scatter", "residual map", "expansion centre", "reconstructed planes",
                           "rig and reconstruction", "reconstruction errors"}
    assert text.count("<img") == len(images)  # every <img> is an embedded PNG
    for alt, a in images.items():
        assert a.shape[0] > 200 and a.shape[1] > 300, alt
        assert a[..., :3].std() > 0.05, alt  # not a blank canvas
    assert not re.search(r'(src|href)="(https?:)?//', text) and "@import" not in text and "url(" not in text


def test_report_without_reconstruction_or_dataset(binocular, tmp_path):
    """A calibration-only folder: the report has the calibration and residuals, and says what is missing."""
    ds, _, out, _ = binocular
    shutil.copy(out / "calibration.json", tmp_path / "calibration.json")
    path = write_report(tmp_path)
    text = path.read_text()
    assert "dataset not found" in text and "no observations found" in text and "<img" not in text
    write_report(tmp_path, ds)  # with the dataset: residuals and the stacking tracks, no reconstruction
    text = path.read_text()
    assert set(_images(text)) == {"residual scatter", "residual map", "expansion centre"}
    assert "no reconstruction" in text and "sim" in text


def test_report_includes_the_model_comparison(binocular, tmp_path):
    _, _, out, _ = binocular
    for name in ("calibration.json", "run.json"):
        shutil.copy(out / name, tmp_path / name)
    md = "## Binocular\n\n| model | rmse (px) | time (ms) |\n|---|--:|--:|\n| ari | 0.0712 | 10 |\n| exact | 0.0702 | 40 |\n"
    (tmp_path / "compare.md").write_text(md)
    png = io.BytesIO()
    mpimg.imsave(png, np.tile(np.linspace(0, 1, 64), (32, 1)), format="png")
    (tmp_path / "residuals_scatter.png").write_bytes(png.getvalue())  # what `ari-sfm compare` writes there
    text = write_report(tmp_path).read_text()
    assert "<h2>Model comparison</h2>" in text and "<h3>Binocular</h3>" in text
    assert _images(text)["model comparison: residuals_scatter"].shape[:2] == (32, 64)
    assert "<td>ari</td><td>0.0712</td>" in text and "---" not in markdown_tables(md)


def test_report_flags_a_reconstruction_older_than_the_last_run(binocular, tmp_path):
    _, _, out, _ = binocular
    for name in ("calibration.json", "points.json", "metrics.json"):
        shutil.copy(out / name, tmp_path / name)
    run = json.loads((out / "run.json").read_text())
    (tmp_path / "run.json").write_text(json.dumps({**run, "reconstruction": None, "reconstruction_skipped": "x"}))
    text = write_report(tmp_path).read_text()
    assert "are older than its calibration" in text and "reconstruction errors" in text


def test_report_cli_and_bad_inputs(binocular, tmp_path):
    _, _, out, _ = binocular
    r = CliRunner().invoke(main, ["report", str(out)])
    assert r.exit_code == 0 and r.output.strip() == f"report: {out / 'report.html'}"
    for folder, needle in ((tmp_path / "none", "no such output folder"),
                           (tmp_path, "calibration.json: missing")):
        r = CliRunner().invoke(main, ["report", str(folder)])
        lines = [ln for ln in r.output.splitlines() if ln.strip()]
        assert r.exit_code == 1 and len(lines) == 1 and lines[0].startswith("error: ") and needle in lines[0], r.output
    (tmp_path / "calibration.json").write_text("{")
    r = CliRunner().invoke(main, ["report", str(tmp_path)])
    assert r.exit_code == 1 and r.output.startswith(f"error: {tmp_path / 'calibration.json'}") and not (tmp_path / "report.html").exists()


def test_run_on_the_single_camera_sample_skips_reconstruction(tmp_path):
    """The README's first command: one camera, no stage frames -> calibration and report only."""
    r = CliRunner().invoke(main, ["run", str(ROOT / "datasets" / "sample"), "-o", str(tmp_path)])
    assert r.exit_code == 0, r.output
    assert "info: reconstruction skipped: the dataset has no reconstruction frames" in r.output
    assert f"report: {tmp_path / 'report.html'}" in r.output and not (tmp_path / "points.json").exists()
    images = _images((tmp_path / "report.html").read_text())
    assert set(images) == {"residual scatter", "residual map", "expansion centre"}


# --------------------------------------------------------------------------- in a browser

PROBE = ("<script>window.addEventListener('load',function(){var im=Array.prototype.slice.call(document.images);"
         "document.body.setAttribute('data-images',im.length);document.body.setAttribute('data-loaded',"
         "im.filter(function(i){return i.complete&&i.naturalWidth>0;}).length);});</script>")
CHROMIUM_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--hide-scrollbars"]


def _chromium() -> str:
    exe = shutil.which("chromium") or shutil.which("chromium-browser")
    if exe is None:
        if os.environ.get("ARI_SFM_REQUIRE_BROWSER"):
            pytest.fail("chromium not found but ARI_SFM_REQUIRE_BROWSER is set: run `bash scripts/setup.sh --tests`")
        pytest.skip("chromium not installed (Debian package chromium; `bash scripts/setup.sh --tests` installs it)")
    return exe


def _loaded_images(exe: str, page: Path, profile: Path) -> tuple[int, int]:
    """(images, images loaded) of a page, counted by a script in Chromium after the load event."""
    probe = page.with_name("probe_" + page.name)
    probe.write_text(page.read_text().replace("</body>", PROBE + "</body>"))
    dom = subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={profile}", "--virtual-time-budget=10000",
                          "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=120).stdout
    found = re.search(r'<body[^>]*data-images="(\d+)"[^>]*data-loaded="(\d+)"', dom)
    assert found, dom[:500]
    return int(found.group(1)), int(found.group(2))


def test_report_renders_in_chromium(binocular, tmp_path):
    exe = _chromium()
    _, _, out, _ = binocular
    page = tmp_path / "report.html"
    shutil.copy(out / "report.html", page)  # file:// page in a folder of its own: nothing else to load
    shot = tmp_path / "shot.png"
    subprocess.run([exe, *CHROMIUM_FLAGS, f"--user-data-dir={tmp_path / 'profile'}", "--window-size=1200,4000",
                    f"--screenshot={shot}", page.as_uri()], capture_output=True, timeout=120, check=True)
    a = mpimg.imread(shot)[..., :3]
    assert a.shape[:2] == (4000, 1200)
    ink = (a.min(axis=2) < 0.9).mean()  # share of pixels that are not (near) white
    assert ink > 0.05 and a.std() > 0.05, f"screenshot looks blank: {ink:.3f} non-white"
    assert _loaded_images(exe, page, tmp_path / "profile") == (6, 6)
    broken = tmp_path / "broken.html"  # the probe itself tells a broken image
    broken.write_text(page.read_text().replace("base64,iVBOR", "base64,AAAA", 1))
    assert _loaded_images(exe, broken, tmp_path / "profile") == (6, 5)
