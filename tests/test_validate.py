"""Tests of envs/data/validate.py: sensor.yaml ranges (through the reader), OpenCV YAML, IMU gaps."""

from __future__ import annotations

import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from data_paths import EUROC_MICRO
from viotb.envs.data.euroc import read_euroc
from viotb.envs.data.validate import bridge_imu_gaps, find_imu_gaps

MICRO = EUROC_MICRO
needs_micro = pytest.mark.skipif(not MICRO.exists(), reason="EuRoC micro dataset not present")


@pytest.fixture()
def micro_copy(tmp_path) -> Path:
    """The micro set's YAML and CSV files (images linked), to edit."""
    if not MICRO.exists():
        pytest.skip("EuRoC micro dataset not present")
    dst = tmp_path / "micro"
    shutil.copytree(
        MICRO,
        dst,
        copy_function=lambda s, d: Path(d).symlink_to(s) if s.endswith(".png") else shutil.copy(s, d),
    )
    return dst


def _edit(path: Path, pattern: str, repl: str) -> None:
    text = path.read_text()
    new = re.sub(pattern, repl, text, count=1, flags=re.M)
    assert new != text, pattern
    path.write_text(new)


@pytest.mark.parametrize(
    ("sensor", "pattern", "repl", "field", "value"),
    [
        ("cam0", r"^intrinsics: .*$", "intrinsics: [0.0, 0.0, 367.2, 248.4]", "intrinsics", "0.0"),
        ("cam0", r"^intrinsics: .*$", "intrinsics: [458.6, -457.3, 367.2, 248.4]", "intrinsics", "-457.3"),
        ("cam0", r"^intrinsics: .*$", "intrinsics: [458.6, 457.3, 900.0, 248.4]", "principal point", "900.0"),
        ("cam0", r"^rate_hz: .*$", "rate_hz: 0", "rate_hz", "0.0"),
        ("imu0", r"^rate_hz: .*$", "rate_hz: -200", "rate_hz", "-200.0"),
        (
            "imu0",
            r"^gyroscope_noise_density: .*$",
            "gyroscope_noise_density: -1e-4",
            "gyroscope_noise_density",
            "-0.0001",
        ),
        (
            "imu0",
            r"^accelerometer_random_walk: .*$",
            "accelerometer_random_walk: -3e-3",
            "accelerometer_random_walk",
            "-0.003",
        ),
    ],
)
def test_sensor_yaml_out_of_range_is_refused_naming_file_field_value(
    micro_copy, sensor, pattern, repl, field, value
):
    yaml_path = micro_copy / "mav0" / sensor / "sensor.yaml"
    _edit(yaml_path, pattern, repl)
    with pytest.raises(ValueError) as info:
        read_euroc(micro_copy)
    message = str(info.value)
    assert str(yaml_path) in message and field in message and value in message, message


def test_opencv_matrix_yaml_is_accepted(micro_copy):
    yaml_path = micro_copy / "mav0" / "cam0" / "sensor.yaml"
    text = yaml_path.read_text().replace(
        "T_BS:\n  cols: 4\n  rows: 4\n", "T_BS: !!opencv-matrix\n  rows: 4\n  cols: 4\n  dt: d\n"
    )
    text = text.replace(
        "intrinsics: [", "intrinsics: !!opencv-matrix\n  rows: 1\n  cols: 4\n  dt: d\n  data: ["
    )
    yaml_path.write_text(text)
    assert "!!opencv-matrix" in yaml_path.read_text()
    ds, ref = read_euroc(micro_copy), read_euroc(MICRO)
    np.testing.assert_array_equal(ds.calib.R_BC, ref.calib.R_BC)
    assert ds.calib.camera == ref.calib.camera


@needs_micro
def test_the_real_micro_set_has_no_imu_gap():
    ds = read_euroc(MICRO)
    assert find_imu_gaps(ds.root / "imu0" / "data.csv", ds.imu_t_ns, ds.imu_rate_hz, 5.0) == []


def test_gaps_are_found_with_their_lines_and_bridged_at_the_nominal_rate(tmp_path):
    t_ns = np.array([0, 5, 10, 1010, 1015], dtype=np.int64) * 1_000_000  # 200 Hz with a 1 s hole
    csv = tmp_path / "data.csv"
    csv.write_text("#timestamp\n" + "".join(f"{t},0,0,0,0,0,9.81\n" for t in t_ns))
    (gap,) = find_imu_gaps(csv, t_ns, 200.0, 5.0)
    assert (gap.index, gap.line0, gap.line1) == (2, 4, 5)
    assert gap.length_s == pytest.approx(1.0)
    assert "lines 4-5" in gap.describe(csv) and "1.000 s" in gap.describe(csv)
    values = np.arange(5.0)[:, None] * np.ones((1, 6))
    t, v, inserted = bridge_imu_gaps(t_ns * 1e-9, values, [gap], 200.0)
    assert inserted == [199] and len(t) == 5 + 199
    assert np.all(np.diff(t) == pytest.approx(0.005))
    np.testing.assert_allclose(v[3 + 99, 0], 2.5, atol=1e-9)  # halfway through the hole
