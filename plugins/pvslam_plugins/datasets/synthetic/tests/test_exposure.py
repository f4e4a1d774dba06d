"""exposure.py: the auto-exposure profile and the exposed copy of a sequence folder."""
import cv2
import numpy as np
import pytest

from pvslam_plugins.datasets.synthetic.exposure import PERIOD, auto_exposure_gain, exposure_copy


def test_gain_profile_ramps_holds_steps_and_repeats():
    assert [auto_exposure_gain(i) for i in (0, 29, 45, 60, 89, 90, 119, 120, 139)] == \
        [1.0, 1.0, 1.25, 1.5, 1.5, 0.7, 0.7, 1.0, 1.0]
    assert auto_exposure_gain(PERIOD + 45) == auto_exposure_gain(45)


def test_exposure_copy_scales_rgb_clips_and_links_the_rest(tmp_path):
    src = tmp_path / "seq"
    (src / "rgb").mkdir(parents=True)
    (src / "groundtruth.txt").write_text("0 0 0 0 0 0 0 1\n")
    for i in range(61):
        cv2.imwrite(str(src / "rgb" / f"{i:06d}.png"), np.full((4, 6, 3), 200 if i == 60 else 100, np.uint8))
    dst = exposure_copy(src, tmp_path / "exposed", brightness=0.9)
    assert (dst / "groundtruth.txt").is_symlink() and (dst / "groundtruth.txt").read_text().startswith("0 0")
    assert int(cv2.imread(str(dst / "rgb" / "000000.png"))[0, 0, 0]) == 90  # 100 x 0.9 x 1.0
    assert int(cv2.imread(str(dst / "rgb" / "000045.png"))[0, 0, 0]) == 112  # 100 x 0.9 x 1.25 = 112.5
    assert int(cv2.imread(str(dst / "rgb" / "000060.png"))[0, 0, 0]) == 255  # 200 x 0.9 x 1.5 clipped
    assert int(cv2.imread(str(src / "rgb" / "000045.png"))[0, 0, 0]) == 100  # the original untouched
    with pytest.raises(FileExistsError):
        exposure_copy(src, dst)
    with pytest.raises(FileNotFoundError, match="no images"):
        exposure_copy(tmp_path / "empty", tmp_path / "x")
