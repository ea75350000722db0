"""The documentation's figures (docs/figures/*.png), made from ari-sfm's own runs on simulated data.

    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/gen_figures.py            # every figure (~5 min on 2 cores)
    OPENBLAS_NUM_THREADS=1 .venv/bin/python docs/gen_figures.py binocular  # one group: binocular, ptv, colmap

Each group runs the commands its tutorial shows (into a temporary folder), then takes the figures from the
report they write (report.html embeds each figure as a PNG) or draws them from the results, shrunk and
reduced to 256 colours so that each file stays under 200 kB (checked). The screenshot of the report needs
Chromium (``chromium`` or ``chromium-browser``, headless). Nothing is fetched from the network.
"""
from __future__ import annotations

import base64
import html
import io
import json
import re
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
FIGURES = ROOT / "docs" / "figures"
MAX_BYTES = 200_000


def ari_sfm(*args: str, cwd: Path) -> str:
    """Run ``ari-sfm ARGS`` (this interpreter's) in ``cwd``; its standard output."""
    done = subprocess.run([sys.executable, "-m", "ari_sfm", *args], cwd=cwd, capture_output=True, text=True,
                          env={**__import__("os").environ, "OPENBLAS_NUM_THREADS": "1"})
    if done.returncode not in (0, 3):
        raise SystemExit(f"ari-sfm {' '.join(args)} failed:\n{done.stderr}")
    print(f"$ ari-sfm {' '.join(args)}\n{done.stdout}", flush=True)
    return done.stdout


def save(image, name: str, width: int = 900) -> Path:
    """Save a PIL image (or PNG bytes) as docs/figures/NAME, at most ``width`` px wide, 256 colours."""
    from PIL import Image

    if isinstance(image, bytes):
        image = Image.open(io.BytesIO(image))
    image = image.convert("RGB")
    if image.width > width:
        image = image.resize((width, round(image.height * width / image.width)), Image.LANCZOS)
    image = image.quantize(colors=256, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)
    path = FIGURES / name
    image.save(path, optimize=True)
    size = path.stat().st_size
    if size > MAX_BYTES:
        raise SystemExit(f"{path}: {size} bytes, over {MAX_BYTES}: make it smaller")
    print(f"wrote {path} ({size // 1000} kB)")
    return path


def report_figures(report: Path) -> dict[str, bytes]:
    """The PNG figures embedded in a report.html, by their alt text."""
    text = report.read_text()
    found = {}
    for m in re.finditer(r'<img[^>]*src="data:image/png;base64,([^"]+)"[^>]*alt="([^"]*)"', text):
        found[html.unescape(m.group(2))] = base64.b64decode(m.group(1))
    for m in re.finditer(r'<img[^>]*alt="([^"]*)"[^>]*src="data:image/png;base64,([^"]+)"', text):
        found.setdefault(html.unescape(m.group(1)), base64.b64decode(m.group(2)))
    return found


def screenshot(page: Path, png: Path, size: tuple[int, int] = (1280, 1500)) -> None:
    """A headless Chromium screenshot of a local page (the network unused)."""
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        raise SystemExit("the report's screenshot needs Chromium (apt-get install chromium)")
    subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
                    "--proxy-server=127.0.0.1:9", f"--window-size={size[0]},{size[1]}",
                    "--virtual-time-budget=8000", f"--screenshot={png}", page.as_uri()],
                   check=True, capture_output=True, timeout=180)


def binocular(work: Path) -> None:
    """The binocular tutorial: run the bundled rig, then the report's picture and figures."""
    from PIL import Image

    shutil.copytree(ROOT / "datasets/binocular", work / "binocular")
    shutil.copy(ROOT / "datasets/binocular_truth.json", work / "binocular_truth.json")
    out = work / "binocular_run"
    ari_sfm("run", "binocular", "-o", "binocular_run", "--truth", "binocular_truth.json", cwd=work)
    figures = report_figures(out / "report.html")
    shot = work / "report_shot.png"
    screenshot(out / "report.html", shot, size=(1100, 760))
    top = Image.open(shot).convert("RGB").crop((0, 0, 1100, 600))  # the rig's table and the recommendations
    rig = Image.open(io.BytesIO(figures["rig and reconstruction"])).convert("RGB")
    rig = rig.resize((top.width - 80, round(rig.height * (top.width - 80) / rig.width)), Image.LANCZOS)
    page = Image.new("RGB", (top.width, top.height + rig.height + 20), "white")
    page.paste(top, (0, 0))
    page.paste(rig, (40, top.height))
    save(page, "report.png", width=800)
    for alt, name in (("residual scatter", "binocular_residuals.png"),
                      ("residuals by image region", "binocular_cells.png"),
                      ("expansion centre", "binocular_expansion.png"),
                      ("rig and reconstruction", "binocular_rig.png"),
                      ("reconstruction errors", "binocular_errors.png")):
        save(figures[alt], name)


def _rig_top_view(cal_path: Path, png: Path, title: str) -> None:
    """Cameras (centre, optical axis) and windows seen from above (world x-z), from a calibration.json."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ari_sfm import load_calibration

    cal = load_calibration(cal_path)
    fig, ax = plt.subplots(figsize=(6.5, 4.6), dpi=110)
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:red"]
    for k, w in enumerate(cal.window_list()):
        n, c = w.normal_world, colours[k % 4]
        plane = w.plane_mm(cal)
        centres = [cal.cameras[name].cam_from_world.inverse().t for name in w.cameras]
        for name, centre in zip(w.cameras, centres):
            axis = cal.cameras[name].cam_from_world.inverse().R[:, 2]
            ax.plot(centre[0], centre[2], "o", color=c)
            ax.annotate("", xy=(centre[0] + 120 * axis[0], centre[2] + 120 * axis[2]), xytext=(centre[0], centre[2]),
                        arrowprops=dict(arrowstyle="->", color=c))
            ax.text(centre[0] + 12, centre[2] - 25, name, fontsize=9, color=c)
        if plane is not None:
            foot = np.mean(centres, axis=0)
            foot = foot + (plane - n @ foot) * n  # the near face below the cameras
            side = np.cross(n, [0.0, 1.0, 0.0])
            side /= np.linalg.norm(side)
            for offset in (0.0, w.interface.thickness_mm):
                a, b = foot + offset * n - 150 * side, foot + offset * n + 150 * side
                ax.plot([a[0], b[0]], [a[2], b[2]], "-", color="0.35", lw=1.5)
            ax.text(foot[0] + 155 * side[0], foot[2] + 155 * side[2], f"window {w.name}", fontsize=9)
    ax.set_aspect("equal")
    ax.set_xlabel("x (mm, world = first camera)")
    ax.set_ylabel("z (mm)")
    ax.set_title(title, fontsize=10)
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def _particle_crop(experiment: Path, detections: Path, png: Path) -> None:
    """A 320 x 240 px crop of one rendered particle image with the detected centres circled."""
    import cv2
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import pyarrow.parquet as pq

    from ari_sfm.io.particles import load_particle_dataset

    experiment_ds = load_particle_dataset(experiment)
    table = pq.read_table(detections).to_pydict()
    camera = sorted(set(table["camera"]))[0]
    frame = min(f for f, c in zip(table["frame"], table["camera"]) if c == camera)
    path = experiment_ds.image_path(camera, frame)
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    h, w = image.shape[:2]
    u0, v0 = w // 2 - 160, h // 2 - 120
    crop = image[v0:v0 + 240, u0:u0 + 320]
    uv = np.array([(u, v) for f, c, u, v in zip(table["frame"], table["camera"], table["u"], table["v"])
                   if c == camera and f == frame and u0 <= u < u0 + 320 and v0 <= v < v0 + 240])
    fig, ax = plt.subplots(figsize=(6.4, 4.9), dpi=100)
    ax.imshow(crop, cmap="gray", vmin=0, vmax=float(np.percentile(crop, 99.8)))
    ax.scatter(uv[:, 0] - u0, uv[:, 1] - v0, s=60, facecolors="none", edgecolors="tab:orange", lw=0.8)
    ax.set_title(f"{camera}, frame {frame}: the detected particle images (circles), 320 x 240 px", fontsize=10)
    ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def _body_from_clicks(png: Path) -> None:
    """test_cavity's body rendered behind a 6 mm wall with particles, a streak and glare; 4 clicked points;
    the points ari_sfm.body identifies from them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ari_sfm.body import find_body
    from ari_sfm.simulate.body_images import cavity_body, cavity_view, render_body_image

    body = cavity_body()
    rendered = render_body_image(cavity_view(), body, seed=1)
    rng = np.random.default_rng(0)
    clicks = {int(i): tuple(rendered.pixels[rendered.ids == i][0] + rng.uniform(-3, 3, 2)) for i in (2, 3, 71, 73)}
    match = find_body(rendered.image, body, clicks)
    fig, ax = plt.subplots(figsize=(6.4, 5.1), dpi=100)
    ax.imshow(rendered.image, cmap="gray")
    ax.scatter(match.pixels[:, 0], match.pixels[:, 1], s=90, facecolors="none", edgecolors="tab:green", lw=1,
               label=f"{len(match.ids)} points identified")
    clicked = np.array(list(clicks.values()))
    ax.scatter(clicked[:, 0], clicked[:, 1], s=140, marker="+", color="tab:red", lw=1.5, label="4 clicks")
    ax.legend(loc="lower right", fontsize=9)
    ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(png)
    plt.close(fig)


def ptv(work: Path) -> None:
    """The PTV tutorial: a tank through two walls, the body from its clicks, particles, self-calibration."""
    from PIL import Image

    ari_sfm("simulate", "tank_opposite", "-o", "tank", cwd=work)
    ari_sfm("calibrate", "tank/dataset", "-o", "tank/cal", cwd=work)
    _rig_top_view(work / "tank/cal/calibration.json", work / "tank_rig.png",
                  "tank_opposite calibrated: two windows, 2 + 2 cameras (seen from above)")
    save(Image.open(work / "tank_rig.png"), "ptv_tank_rig.png", width=700)
    _body_from_clicks(work / "body.png")
    save(Image.open(work / "body.png"), "ptv_body_clicks.png", width=640)
    ari_sfm("simulate", "particles", "--windows", "2", "--particles", "1000", "--frames", "6", "--look", "tank",
            "-o", "ptv", cwd=work)
    ari_sfm("calibrate", "ptv/calibration", "-o", "ptv/cal", "--model", "exact", cwd=work)
    ari_sfm("detect-particles", "ptv/experiment", "-o", "ptv/det", "--workers", "0", cwd=work)
    _particle_crop(work / "ptv/experiment", work / "ptv/det/particles.parquet", work / "crop.png")
    save(Image.open(work / "crop.png"), "ptv_particles.png", width=640)
    ari_sfm("self-calibrate", "ptv/experiment", "--calibration", "ptv/cal/calibration.json", "-o", "ptv/selfcal",
            "--frames", "6", "--workers", "0", cwd=work)
    ari_sfm("report", "ptv/selfcal", cwd=work)
    figures = report_figures(work / "ptv/selfcal/report.html")
    disparity = [alt for alt in figures if "disparity" in alt.lower()]
    save(figures[disparity[0]], "ptv_disparity.png")


def colmap(work: Path) -> None:
    """The COLMAP tutorial: a rendered port survey, sfm, and the refinement's per-image residuals."""
    import matplotlib
    from PIL import Image

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    ari_sfm("simulate", "port_survey", "-o", "survey", cwd=work)
    first = sorted((work / "survey/images").iterdir())[0]
    save(Image.open(first), "colmap_survey_image.png", width=480)
    truth = json.loads((work / "survey/truth.json").read_text())
    window = work / "WINDOW.yaml"
    window.write_text(_window_yaml(truth))
    first_last, baseline_mm = _baseline(truth)
    ari_sfm("sfm", "survey/images", "--window", str(window), "-o", "survey/out", "--baseline", *first_last,
            f"{baseline_mm:.1f}", cwd=work)
    refine = json.loads((work / "survey/out/refined/refine.json").read_text())
    before = refine["before"]["per_image_rms_px"]
    after = refine["after"]["per_image_rms_px"]
    names = sorted(before)
    fig, ax = plt.subplots(figsize=(7, 3.2), dpi=110)
    x = np.arange(len(names))
    ax.bar(x - 0.2, [before[n] for n in names], 0.4, label="COLMAP's pinhole model")
    ax.bar(x + 0.2, [after[n] for n in names], 0.4, label="refine-colmap (exact Snell)")
    ax.set_xticks(x, [n.rsplit(".", 1)[0][-3:] for n in names], fontsize=8)
    ax.set_xlabel("image")
    ax.set_ylabel("reprojection RMS (px)")
    ax.legend(fontsize=9)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    fig.savefig(work / "refine.png")
    plt.close(fig)
    save(Image.open(work / "refine.png"), "colmap_refine.png", width=770)


def _window_yaml(truth: dict) -> str:
    """WINDOW.yaml of the simulated survey: its port (thickness, indices), a housing per camera."""
    port = truth["interface"]
    return (f"interface: {{thickness_mm: {port['thickness_mm']}, index: {port['index']}, "
            f"medium_index: {port['medium_index']}}}\nmount: camera\n")


def _baseline(truth: dict) -> tuple[tuple[str, str], float]:
    """The scale as navigation gives it: the first and last images and their camera centres' distance (mm)."""
    from ari_sfm.geometry import Pose

    names = sorted(truth["images"])
    a, b = (Pose.from_json(truth["images"][n]).inverse().t for n in (names[0], names[-1]))
    return (names[0], names[-1]), float(np.linalg.norm(b - a))


GROUPS = {"binocular": binocular, "ptv": ptv, "colmap": colmap}


def main(names: list[str]) -> None:
    FIGURES.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="ari_sfm_figures_") as tmp:
        for name in names or list(GROUPS):
            work = Path(tmp) / name
            work.mkdir()
            GROUPS[name](work)


if __name__ == "__main__":
    main(sys.argv[1:])
