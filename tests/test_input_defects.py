"""The defects found by fuzzing the command line (issue 10, item 7): each bad input gives one line
naming the file (or option) and the field, exit 1, and no result file."""
from __future__ import annotations

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from ari_sfm.cli import main
from ari_sfm.detection import detect_dataset
from ari_sfm.errors import AriSfmError
from ari_sfm.io import load_dataset

from test_detection import W, H, write_dataset, checker_views  # noqa: F401 - the module fixture


@pytest.mark.parametrize("scale", [0.5, 2.0])
def test_image_of_another_size_than_image_size_is_an_error_naming_it(checker_views, tmp_path, scale):  # noqa: F811
    """Half size calibrated silently gave 0.43 px instead of 0.10; double size wrote an unloadable file."""
    root = write_dataset(tmp_path / "ds", [checker_views[k][0] for k in range(4)])
    resized = cv2.resize(checker_views[2][0], (int(W * scale), int(H * scale)), interpolation=cv2.INTER_AREA)
    cv2.imwrite(str(root / "img" / "c2.png"), resized)
    with pytest.raises(AriSfmError) as info:
        detect_dataset(load_dataset(root), workers=2, progress=False)
    assert info.value.path == str(root / "img" / "c2.png")
    assert f"image is {int(W * scale)} x {int(H * scale)} px" in info.value.message
    assert f"cameras.cam0.image_size [{W}, {H}]" in info.value.message
    r = CliRunner().invoke(main, ["calibrate", str(root), "-o", str(tmp_path / "out")])
    last = r.output.strip().splitlines()[-1]  # after the progress bar
    assert r.exit_code == 1 and last.startswith(f"error: {root / 'img' / 'c2.png'}: image is")
    assert not (tmp_path / "out" / "calibration.json").exists()
    assert not (tmp_path / "out" / "observations.json").exists()
