"""A run that never initialises (identical frames: no parallax) says so and exits non-zero."""
import json

import cv2
import numpy as np

from pvslam_core.cli import EXIT_NO_MOTION, main


def test_identical_frames_exit_non_zero(tmp_path, capsys):
    frames = tmp_path / "frames"
    frames.mkdir()
    img = np.random.default_rng(0).integers(0, 255, (120, 160, 3), dtype=np.uint8)
    img = cv2.GaussianBlur(img, (5, 5), 1.5)  # textured, so tracking itself works
    for k in range(12):
        cv2.imwrite(str(frames / f"{k:04d}.png"), img)
    calib = tmp_path / "calib.txt"
    calib.write_text("150 150 79.5 59.5\n")
    code = main(["run", str(frames), "--calib", str(calib), "--output-dir", str(tmp_path / "runs"), "-q"])
    err = capsys.readouterr().err
    assert code == EXIT_NO_MOTION and "no motion was estimated" in err
    run_dir = next((tmp_path / "runs").iterdir())
    assert json.loads((run_dir / "metrics.json").read_text())["tracking"]["initialized"] is False
    assert "never initialised" in (run_dir / "log.txt").read_text()
