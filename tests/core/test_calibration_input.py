"""Calibrations with inf/NaN, non-positive focal lengths or a principal point far outside the image are rejected
with an error that names the file and the value."""
from __future__ import annotations

import math

import pytest

from pvslam_core.datasets.base import DatasetError
from pvslam_core.datasets.calib import calibration_from_option, read_calibration
from pvslam_core.types import Intrinsics


@pytest.mark.parametrize("kw, needle", [
    (dict(fx=math.inf), "fx=inf"),
    (dict(fy=math.nan), "fy=nan"),
    (dict(cx=-math.inf), "cx=-inf"),
    (dict(cy=math.nan), "cy=nan"),
    (dict(fx=0.0), "fx=0.0"),
    (dict(fy=-100.0), "fy=-100.0"),
    (dict(cx=5000.0), "cx=5000.0"),
    (dict(cy=-400.0), "cy=-400.0"),
    (dict(dist=(0.1, math.nan, 0.0, 0.0)), "k2=nan"),
])
def test_intrinsics_reject_bad_values(kw, needle):
    args = dict(fx=500.0, fy=500.0, cx=319.5, cy=239.5, width=640, height=480)
    args.update(kw)
    with pytest.raises(ValueError) as err:
        Intrinsics(**args)
    assert needle in str(err.value)


def test_intrinsics_accept_off_centre_principal_point_inside_the_margin():
    Intrinsics(500.0, 500.0, 700.0, -100.0, 640, 480)  # within half an image of the border: a crop/shift lens
    k = Intrinsics(500.0, 500.0, 319.5, 239.5, 640, 480)
    assert k.scaled(0.125).cx == pytest.approx((319.5 + 0.5) * 0.125 - 0.5)
    assert k.cropped(10, 20, 600, 440).cx == pytest.approx(309.5)


@pytest.mark.parametrize("text, needle", [
    ("inf 500 319.5 239.5\n", "fx=inf"),
    ("500 500 nan 239.5\n", "cx=nan"),
    ("500 500 319.5 239.5 0.1 NaN 0 0\n", "nan"),
    ("0 500 319.5 239.5\n", "fx=0.0"),
    ("500 500 319.5 9000\n", "cy=9000.0"),
])
def test_calibration_file_with_bad_values_names_the_file_and_value(tmp_path, text, needle):
    p = tmp_path / "calib.txt"
    p.write_text("# fx fy cx cy\n" + text)
    with pytest.raises(DatasetError) as err:
        read_calibration(p, 640, 480)
    msg = str(err.value)
    assert str(p) in msg and needle in msg.lower()


def test_non_finite_value_names_the_line(tmp_path):
    p = tmp_path / "calib.txt"
    p.write_text("# comment\n500 500\n319.5 inf\n")
    with pytest.raises(DatasetError) as err:
        read_calibration(p, 640, 480)
    assert f"{p}:3" in str(err.value) and "inf" in str(err.value) and "finite" in str(err.value)


def test_calibration_values_in_a_config(tmp_path):
    with pytest.raises(DatasetError) as err:
        calibration_from_option([500, 500, float("nan"), 239.5], 640, 480, owner="images reader")
    assert "images reader config 'calib'" in str(err.value) and "cx=nan" in str(err.value)
