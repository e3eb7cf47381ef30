"""Tests of the EuRoC ASL reader/writer (envs/euroc.py), on real data and synthetic round trips."""

from __future__ import annotations

import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest
from data_paths import EUROC_MICRO
from viotb.envs.data.euroc import load_image, read_euroc
from viotb.envs.data.euroc_writer import write_euroc
from viotb.vio.camera import CameraCalibration, PinholeCamera
from viotb.vio.types import ImuNoise, ImuSeries, TrajectoryArrays

MICRO = EUROC_MICRO
needs_micro = pytest.mark.skipif(not MICRO.exists(), reason="EuRoC micro dataset not present")


@needs_micro
def test_real_micro_dataset_loads():
    ds = read_euroc(MICRO)
    assert len(ds) == 95 and len(ds.cam_t_s) == 95
    assert len(ds.imu) == 29120
    assert np.all(np.diff(ds.imu_t_ns) > 0) and np.all(np.diff(ds.cam_t_ns) > 0)
    assert ds.cam_t_ns[0] == 1403715273262142976 and ds.imu_t_ns[0] == 1403715273262142976
    np.testing.assert_allclose(ds.cam_t_s[1] - ds.cam_t_s[0], 0.05, atol=1e-6)
    cam = ds.calib.camera
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (458.654, 457.296, 367.215, 248.375)
    assert cam.distortion == (-0.28340811, 0.07395907, 0.00019359, 1.76187114e-05)
    assert (cam.width, cam.height) == (752, 480)
    np.testing.assert_array_equal(ds.calib.R_BC[0], [0.0148655429818, -0.999880929698, 0.00414029679422])
    np.testing.assert_array_equal(ds.calib.p_BC, [-0.0216401454975, -0.064676986768, 0.00981073058949])
    assert ds.calib.rate_hz == 20.0 and ds.calib.time_offset_s == 0.0
    assert ds.imu_noise == ImuNoise(1.6968e-4, 1.9393e-5, 2.0e-3, 3.0e-3)
    assert ds.imu_rate_hz == 200.0
    # First IMU row as printed in imu0/data.csv.
    np.testing.assert_array_equal(
        ds.imu.gyro_B_rad_s[0], [-0.0020943951023931952, 0.017453292519943295, 0.07749261878854824]
    )
    np.testing.assert_array_equal(
        ds.imu.accel_B_m_s2[0], [9.0874956666666655, 0.13075533333333333, -3.6938381666666662]
    )
    assert len(ds.groundtruth) == 2895
    np.testing.assert_array_equal(ds.groundtruth.p_WB[0], [0.878895, 2.1834, 0.948427])
    np.testing.assert_allclose(np.linalg.norm(ds.groundtruth.quat_wxyz_WB, axis=1), 1.0, atol=1e-12)
    np.testing.assert_array_equal(ds.gt_gyro_bias[0], [-0.00224703, 0.0215352, 0.0770299])
    assert ds.landmarks_W is None
    for i in (0, 94):
        image = load_image(ds, i)
        assert image.shape == (480, 752) and image.dtype == np.uint8
    # The mav0 folder itself is accepted too.
    assert len(read_euroc(MICRO / "mav0")) == 95


def _synthetic(rng: np.random.Generator):
    n, f, m = 300, 6, 40
    t_imu = np.arange(n) * 0.005
    imu = ImuSeries(t_imu, rng.normal(size=(n, 3)), rng.normal(size=(n, 3)) + [0, 0, 9.81], np.zeros(n, bool))
    cam = PinholeCamera(32, 24, 20.1, 20.3, 15.5, 11.5, (0.01, -0.002, 1e-4, -2e-4))
    angle = 0.3
    R_BC = np.array(
        [[np.cos(angle), -np.sin(angle), 0.0], [np.sin(angle), np.cos(angle), 0.0], [0.0, 0.0, 1.0]]
    )
    calib = CameraCalibration(cam, R_BC, np.array([0.07, 0.0, -0.01]), 0.0125, 20.0)
    frames = [(0.1 + 0.05 * k, rng.integers(0, 256, size=(24, 32), dtype=np.uint8)) for k in range(f)]
    quat = rng.normal(size=(m, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    gt = TrajectoryArrays(np.arange(m) * 0.0375, rng.normal(size=(m, 3)), quat, rng.normal(size=(m, 3)))
    return imu, frames, calib, gt, rng.normal(size=(m, 3)), rng.normal(size=(m, 3)), rng.normal(size=(12, 3))


def test_write_read_round_trip_exact(tmp_path):
    rng = np.random.default_rng(0)
    imu, frames, calib, gt, bw, ba, landmarks = _synthetic(rng)
    noise = ImuNoise(1e-3, 2e-5, 3e-3, 4e-4)
    mav0 = write_euroc(
        tmp_path / "rec", imu, iter(frames), calib, noise, gt, bw, ba, landmarks, imu_rate_hz=200.0
    )
    assert mav0 == tmp_path / "rec" / "mav0"
    ds = read_euroc(tmp_path / "rec")
    np.testing.assert_array_equal(ds.imu_t_ns, np.arange(300, dtype=np.int64) * 5_000_000)
    np.testing.assert_array_equal(ds.cam_t_ns, [100_000_000 + 50_000_000 * k for k in range(6)])
    np.testing.assert_array_equal(ds.gt_t_ns, np.arange(40, dtype=np.int64) * 37_500_000)
    np.testing.assert_array_equal(ds.imu.gyro_B_rad_s, imu.gyro_B_rad_s)
    np.testing.assert_array_equal(ds.imu.accel_B_m_s2, imu.accel_B_m_s2)
    np.testing.assert_allclose(ds.imu.t_s, imu.t_s, atol=1e-15)
    for k, (_, image) in enumerate(frames):
        np.testing.assert_array_equal(load_image(ds, k), image)
    assert ds.calib.camera == calib.camera
    np.testing.assert_array_equal(ds.calib.R_BC, calib.R_BC)
    np.testing.assert_array_equal(ds.calib.p_BC, calib.p_BC)
    assert ds.calib.time_offset_s == 0.0125 and ds.calib.rate_hz == 20.0
    assert ds.imu_noise == noise and ds.imu_rate_hz == 200.0
    np.testing.assert_array_equal(ds.groundtruth.p_WB, gt.p_WB)
    np.testing.assert_allclose(ds.groundtruth.quat_wxyz_WB, gt.quat_wxyz_WB, atol=1e-15)
    np.testing.assert_array_equal(ds.groundtruth.v_WB, gt.v_WB)
    np.testing.assert_array_equal(ds.gt_gyro_bias, bw)
    np.testing.assert_array_equal(ds.gt_accel_bias, ba)
    np.testing.assert_array_equal(ds.landmarks_W, landmarks)
    header = (mav0 / "imu0" / "data.csv").read_text().splitlines()[0]
    assert header.startswith("#timestamp [ns],w_RS_S_x [rad s^-1]") and header.endswith("a_RS_S_z [m s^-2]")
    assert (mav0 / "cam0" / "sensor.yaml").read_text().startswith("%YAML:1.0\n")


def test_writer_rejects_bad_input(tmp_path):
    rng = np.random.default_rng(0)
    imu, frames, calib, *_ = _synthetic(rng)
    noise = ImuNoise()
    with pytest.raises(ValueError, match="frame 0 must be uint8 of shape"):
        write_euroc(tmp_path / "a", imu, [(0.0, np.zeros((10, 10), np.uint8))], calib, noise)
    with pytest.raises(ValueError, match="camera times must strictly increase"):
        write_euroc(tmp_path / "b", imu, [frames[1], frames[0]], calib, noise)
    back = ImuSeries(imu.t_s[::-1].copy(), imu.gyro_B_rad_s, imu.accel_B_m_s2, imu.saturated)
    with pytest.raises(ValueError, match="IMU times must strictly increase"):
        write_euroc(tmp_path / "c", back, frames, calib, noise)


# ---------------------------------------------------------------------------------------------------------
# Bad inputs, written into small copies of the real dataset (first rows only; PNGs symlinked).


@pytest.fixture
def small_copy(tmp_path) -> Path:
    if not MICRO.exists():
        pytest.skip("EuRoC micro dataset not present")
    src, dst = MICRO / "mav0", tmp_path / "ds" / "mav0"
    for sub in ("cam0/data", "imu0", "state_groundtruth_estimate0"):
        (dst / sub).mkdir(parents=True)
    for name in ("cam0/sensor.yaml", "imu0/sensor.yaml", "state_groundtruth_estimate0/sensor.yaml"):
        shutil.copy(src / name, dst / name)
    for name, rows in (
        ("cam0/data.csv", 5),
        ("imu0/data.csv", 100),
        ("state_groundtruth_estimate0/data.csv", 10),
    ):
        lines = (src / name).read_text().splitlines(keepends=True)
        (dst / name).write_text("".join(lines[: rows + 1]))
    for line in (dst / "cam0/data.csv").read_text().splitlines()[1:]:
        png = line.split(",")[1]
        (dst / "cam0/data" / png).symlink_to(src / "cam0/data" / png)
    return tmp_path / "ds"


def _edit_line(path: Path, line_no: int, new_text: str) -> None:
    lines = path.read_text().splitlines()
    lines[line_no - 1] = new_text
    path.write_text("\n".join(lines) + "\n")


def test_small_copy_is_valid(small_copy):
    ds = read_euroc(small_copy)
    assert len(ds) == 5 and len(ds.imu) == 100 and len(ds.groundtruth) == 10
    assert load_image(ds, 4).shape == (480, 752)


def test_missing_folder_and_files(small_copy, tmp_path):
    with pytest.raises(FileNotFoundError, match="not found"):
        read_euroc(tmp_path / "nope")
    (tmp_path / "empty").mkdir()
    with pytest.raises(FileNotFoundError, match="no mav0"):
        read_euroc(tmp_path / "empty")
    (small_copy / "mav0/imu0/data.csv").unlink()
    with pytest.raises(FileNotFoundError, match=r"imu0/data\.csv"):
        read_euroc(small_copy)


def test_missing_image_names_row(small_copy):
    png = (small_copy / "mav0/cam0/data.csv").read_text().splitlines()[3].split(",")[1]
    (small_copy / "mav0/cam0/data" / png).unlink()
    with pytest.raises(FileNotFoundError, match=rf"cam0/data\.csv, line 4: image file not found: .*{png}"):
        read_euroc(small_copy)


def test_corrupt_png(small_copy):
    ds = read_euroc(small_copy)
    path = ds.image_paths[2]
    path.unlink()  # replace the symlink by a corrupt copy
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 10)
    with pytest.raises(ValueError, match=rf"{path.name}: cannot decode"):
        load_image(ds, 2)


def test_image_size_mismatch(small_copy):
    yaml_path = small_copy / "mav0/cam0/sensor.yaml"
    yaml_path.write_text(yaml_path.read_text().replace("resolution: [752, 480]", "resolution: [640, 480]"))
    ds = read_euroc(small_copy)
    with pytest.raises(ValueError, match="image size 752x480 does not match the resolution 640x480"):
        load_image(ds, 0)


def test_truncated_row(small_copy):
    path = small_copy / "mav0/imu0/data.csv"
    _edit_line(path, 7, "1403715273292142848,-0.002,0.017")
    with pytest.raises(ValueError, match=r"imu0/data\.csv, line 7: expected 7 comma-separated values, got 3"):
        read_euroc(small_copy)


def test_malformed_value(small_copy):
    path = small_copy / "mav0/imu0/data.csv"
    lines = path.read_text().splitlines()
    fields = lines[9].split(",")
    fields[4] = "9.0x"
    _edit_line(path, 10, ",".join(fields))
    with pytest.raises(ValueError, match=r"imu0/data\.csv, line 10, column 5: not a number: '9\.0x'"):
        read_euroc(small_copy)


def test_nan_and_inf_values(small_copy):
    path = small_copy / "mav0/state_groundtruth_estimate0/data.csv"
    fields = path.read_text().splitlines()[5].split(",")
    fields[2] = "nan"
    _edit_line(path, 6, ",".join(fields))
    with pytest.raises(
        ValueError, match=r"state_groundtruth_estimate0/data\.csv, line 6, column 3: non-finite"
    ):
        read_euroc(small_copy)
    fields[2] = "inf"
    _edit_line(path, 6, ",".join(fields))
    with pytest.raises(ValueError, match="line 6, column 3: non-finite value 'inf'"):
        read_euroc(small_copy)


def test_non_monotonic_and_duplicate_timestamps(small_copy):
    path = small_copy / "mav0/imu0/data.csv"
    original = path.read_text()
    lines = original.splitlines()
    t_prev = lines[19].split(",")[0]
    fields = lines[20].split(",")
    fields[0] = t_prev
    _edit_line(path, 21, ",".join(fields))
    with pytest.raises(ValueError, match=rf"lines 20-21: duplicate timestamps {t_prev} then {t_prev}"):
        read_euroc(small_copy)
    path.write_text(original)
    fields[0] = str(int(t_prev) - 1)
    _edit_line(path, 21, ",".join(fields))
    with pytest.raises(ValueError, match=r"imu0/data\.csv, lines 20-21: non-monotonic timestamps"):
        read_euroc(small_copy)


def test_bad_camera_csv_timestamp(small_copy):
    path = small_copy / "mav0/cam0/data.csv"
    lines = path.read_text().splitlines()
    lines[1], lines[2] = lines[2], lines[1]
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError, match=r"cam0/data\.csv, lines 2-3: non-monotonic"):
        read_euroc(small_copy)


def test_bad_yaml_fields(small_copy):
    yaml_path = small_copy / "mav0/cam0/sensor.yaml"
    text = yaml_path.read_text()
    yaml_path.write_text(
        text.replace("intrinsics: [458.654, 457.296, 367.215, 248.375]", "intrinsics: [1, 2, 3]")
    )
    with pytest.raises(ValueError, match=r"sensor\.yaml: field 'intrinsics' must hold 4 finite numbers"):
        read_euroc(small_copy)
    yaml_path.write_text(text.replace("0.0148655429818, -0.999880929698", "0.5, -0.999880929698"))
    with pytest.raises(ValueError, match="T_BS rotation block is not a rotation"):
        read_euroc(small_copy)
    imu_yaml = small_copy / "mav0/imu0/sensor.yaml"
    yaml_path.write_text(text)
    imu_yaml.write_text(imu_yaml.read_text().replace("gyroscope_noise_density", "gyro_density"))
    with pytest.raises(ValueError, match="missing field 'gyroscope_noise_density'"):
        read_euroc(small_copy)


def test_load_image_index_16bit_and_float(small_copy, tmp_path):
    ds = read_euroc(small_copy)
    with pytest.raises(IndexError, match="out of range"):
        load_image(ds, 5)
    original = load_image(ds, 1)
    path = ds.image_paths[1]
    path.unlink()
    # A 16-bit PNG as TUM-VI's EuRoC export writes it (8-bit value v stored as 257 v, plus low-byte noise).
    low = np.random.default_rng(0).integers(0, 256, original.shape)
    cv2.imwrite(str(path), (original.astype(np.uint16) * 256 + low.astype(np.uint16)))
    np.testing.assert_array_equal(load_image(ds, 1), original)
    # A float image (a TIFF under a .png name: OpenCV decodes by content) is refused, naming the dtype.
    path.unlink()
    ok, tiff = cv2.imencode(".tiff", original.astype(np.float32))
    assert ok
    path.write_bytes(tiff.tobytes())
    with pytest.raises(ValueError, match="expected an 8-bit or 16-bit image, got dtype float32"):
        load_image(ds, 1)
