"""Tests of open-loop recording (envs/record.py): determinism and EuRoC round trip."""

from __future__ import annotations

import os

os.environ.setdefault("MUJOCO_GL", "egl")

import filecmp
from pathlib import Path

import numpy as np
import pytest
from viotb.envs.data.euroc import load_image, read_euroc
from viotb.envs.data.record import record_scenario
from viotb.envs.scenarios.registry import get_scenario
from viotb.vio.lie import quat_wxyz_to_rotmat


def _files(root: Path) -> list[Path]:
    return sorted(p.relative_to(root) for p in root.rglob("*") if p.is_file())


def test_same_seed_gives_byte_identical_dataset(tmp_path):
    calls = []
    a = record_scenario(
        "hover", tmp_path / "a", seed=3, seconds=1.0, progress=lambda d, t: calls.append((d, t))
    )
    b = record_scenario("hover", tmp_path / "b", seed=3, seconds=1.0)
    c = record_scenario("hover", tmp_path / "c", seed=4, seconds=1.0)
    files = _files(tmp_path / "a")
    assert files == _files(tmp_path / "b")
    assert sum(f.suffix == ".png" for f in files) == a["frames"] == 21
    _, mismatch, errors = filecmp.cmpfiles(
        tmp_path / "a", tmp_path / "b", [str(f) for f in files], shallow=False
    )
    assert mismatch == [] and errors == []
    # Another seed changes the IMU noise and the pixel noise.
    assert (tmp_path / "a/mav0/imu0/data.csv").read_bytes() != (
        tmp_path / "c/mav0/imu0/data.csv"
    ).read_bytes()
    png = files[[f.suffix for f in files].index(".png")]
    assert (tmp_path / "a" / png).read_bytes() != (tmp_path / "c" / png).read_bytes()
    assert calls[-1] == (21, 21) and len(calls) == 21
    assert a["imu_samples"] == b["imu_samples"] == c["imu_samples"] == 201


def test_short_record_round_trips_through_read_euroc(tmp_path):
    result = record_scenario("circle", tmp_path, seed=0, seconds=2.0)
    assert set(result) >= {
        "frames",
        "imu_samples",
        "path_length_m",
        "seconds",
        "scenario",
        "seed",
        "realtime_factor",
        "out",
    }
    ds = read_euroc(result["out"])
    scenario = get_scenario("circle")
    assert len(ds) == result["frames"] == 41
    assert len(ds.imu) == result["imu_samples"] == 401
    np.testing.assert_array_equal(ds.cam_t_ns, np.arange(41, dtype=np.int64) * 50_000_000)
    np.testing.assert_array_equal(ds.imu_t_ns, np.arange(401, dtype=np.int64) * 5_000_000)
    assert (ds.calib.camera.width, ds.calib.camera.height) == (scenario.camera.width, scenario.camera.height)
    assert ds.imu_noise.gyro_noise_density_rad_s_sqrthz == 1.6968e-4
    # Ground truth: path length and truth at the IMU rate, biases within the preset's turn-on spread.
    p = ds.groundtruth.p_WB
    np.testing.assert_allclose(
        np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)), result["path_length_m"], rtol=1e-12
    )
    assert len(ds.groundtruth) == 401 and ds.gt_gyro_bias.shape == (401, 3)
    assert np.abs(ds.gt_gyro_bias).max() < 0.1
    # Gyro minus truth rate minus true bias is white noise of sigma density * sqrt(rate) (+ scale errors).
    traj = scenario.make_trajectory(2.0)
    truth = traj.sample_many(ds.imu.t_s)
    residual = ds.imu.gyro_B_rad_s - truth.omega_B - ds.gt_gyro_bias
    sigma = 1.6968e-4 * np.sqrt(200.0)
    assert np.abs(residual).max() < 6 * sigma + 0.01 * np.abs(truth.omega_B).max()
    # Quaternions in the file describe the true attitude.
    R0 = quat_wxyz_to_rotmat(ds.groundtruth.quat_wxyz_WB[100])
    np.testing.assert_allclose(R0, truth.R_WB[100], atol=1e-12)
    assert ds.landmarks_W is not None and ds.landmarks_W.shape == (3000, 3)
    image = load_image(ds, 20)
    assert image.shape == (240, 320) and image.std() > 10.0  # textured room, not a blank frame


def test_time_offset_scenario_stamps_and_headset(tmp_path):
    result = record_scenario("circle-time-offset", tmp_path / "off", seed=0, seconds=1.0)
    ds = read_euroc(result["out"])
    assert ds.calib.time_offset_s == 0.015
    # Camera stamps stay on the 20 Hz camera grid; exposures t_cam + 0.015 must lie inside [0, 1] s.
    np.testing.assert_array_equal(ds.cam_t_ns, np.arange(20, dtype=np.int64) * 50_000_000)
    head = record_scenario("head-look-around", tmp_path / "head", seed=0, seconds=1.0)
    ds_head = read_euroc(head["out"])
    assert len(ds_head) == 31  # 30 Hz headset camera
    assert load_image(ds_head, 0).std() > 10.0


def test_bad_requests(tmp_path):
    with pytest.raises(ValueError, match="unknown scenario"):
        record_scenario("nope", tmp_path)
    with pytest.raises(ValueError, match="seconds must be positive"):
        record_scenario("hover", tmp_path, seconds=-1.0)


def test_failure_recordings_carry_their_wrong_calibration_and_imu_faults(tmp_path):
    """``fail-*`` recordings hold what the failure needs: the wrong calibration file, the faulty IMU."""
    from viotb.envs.sim.render import camera_calibration
    from viotb.envs.sim.simulation import Simulation
    from viotb.models.constants import ONBOARD_CAMERA, QUAD_BODY
    from viotb.vio.lie import log_so3

    sim = Simulation("quadrotor", "textured_room")
    true_R_BC = camera_calibration(sim.model, ONBOARD_CAMERA, QUAD_BODY, 320, 240).R_BC
    ext = read_euroc(record_scenario("fail-extrinsic", tmp_path / "ext", seed=0, seconds=1.0)["out"])
    angle = float(np.linalg.norm(log_so3(true_R_BC.T @ ext.calib.R_BC)))
    assert angle == pytest.approx(np.deg2rad(2.0), abs=1e-9)
    # The camera runs 10 ms late, the calibration file says 0.
    off = read_euroc(record_scenario("fail-time-offset", tmp_path / "off", seed=0, seconds=1.0)["out"])
    assert off.calib.time_offset_s == 0.0 and get_scenario("fail-time-offset").camera.time_offset_s == 0.01
    # Bad init: +0.3 rad/s on every gyro axis and a 5 % accelerometer scale; at rest |a| reads 1.05 g.
    bad = read_euroc(record_scenario("fail-bad-init", tmp_path / "bad", seed=0, seconds=1.0)["out"])
    still = bad.imu.t_s < 1.0
    # (measured 0.329 / 0.283 / 0.315: the part's own turn-on bias and scale errors spread the axes)
    np.testing.assert_allclose(bad.imu.gyro_B_rad_s[still].mean(axis=0), 0.3, atol=0.05)
    assert np.linalg.norm(bad.imu.accel_B_m_s2[still].mean(axis=0)) == pytest.approx(1.05 * 9.81, rel=0.01)


@pytest.mark.slow
def test_motion_blur_costs_klt_tracks_during_a_spin(tmp_path):
    """``fast-rotation`` vs ``fast-rotation-blur`` (45 ms exposure), 5 s, KLT + MSCKF.

    Measured (seed 0) during the 3 rad/s part (2.5-4 s): 180 tracked features sharp, 91 (min 63) blurred;
    feature updates 476 -> 245.
    """
    from viotb.envs.data.evaluate import EvalOptions, run_monitored

    tracked = {}
    for name in ("fast-rotation", "fast-rotation-blur"):
        ds = read_euroc(record_scenario(name, tmp_path / name, seed=0, seconds=5.0)["out"])
        run = run_monitored(ds, EvalOptions())
        spin = [
            h.tracked_features for t, h in zip(run.frame_t_imu_s, run.health, strict=True) if 2.5 < t < 4.0
        ]
        tracked[name] = float(np.mean(spin))
    assert tracked["fast-rotation-blur"] < 0.7 * tracked["fast-rotation"], tracked


def test_resolution_and_rates_are_recorded_in_the_sensor_files(tmp_path):
    out = tmp_path / "euroc"
    res = record_scenario(
        "hover", out, seconds=0.5, resolution=(752, 480), camera_rate_hz=10.0, imu_rate_hz=400.0
    )
    assert (res["frames"], res["imu_samples"], res["resolution"]) == (6, 201, [752, 480])
    ds = read_euroc(out)
    assert (ds.calib.camera.width, ds.calib.camera.height, ds.calib.rate_hz, ds.imu_rate_hz) == (
        752,
        480,
        10.0,
        400.0,
    )
    assert load_image(ds, 0).shape == (480, 752)
    big = record_scenario("hover", tmp_path / "big", seconds=0.05, resolution=(1024, 768))
    assert big["resolution"] == [1024, 768]  # beyond the MJCF's 752x480 offscreen buffer


def test_interrupted_record_leaves_nothing_that_looks_valid(tmp_path):
    def interrupt(done: float, total: float) -> None:
        if done >= 5:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        record_scenario("hover", tmp_path / "rec", seconds=2.0, progress=interrupt)
    assert list(tmp_path.iterdir()) == []


def test_streamed_imu_chunks_join_seamlessly(tmp_path, monkeypatch):
    import viotb.envs.data.record as record_module

    whole = record_scenario("circle", tmp_path / "whole", seed=1, seconds=1.0)
    monkeypatch.setattr(record_module, "IMU_CHUNK_SAMPLES", 64)  # 201 samples in 4 chunks
    chunked = record_scenario("circle", tmp_path / "chunked", seed=1, seconds=1.0)
    assert whole["path_length_m"] == pytest.approx(chunked["path_length_m"], rel=1e-12)
    for rel in ("cam0/data.csv", "state_groundtruth_estimate0/data.csv"):
        a = (tmp_path / "whole" / "mav0" / rel).read_text()
        assert a == (tmp_path / "chunked" / "mav0" / rel).read_text(), rel
    imu_a, imu_b = (read_euroc(tmp_path / d).imu for d in ("whole", "chunked"))
    np.testing.assert_array_equal(imu_a.t_s, imu_b.t_s)
    np.testing.assert_array_equal(imu_a.gyro_B_rad_s, imu_b.gyro_B_rad_s)
    np.testing.assert_array_equal(imu_a.accel_B_m_s2, imu_b.accel_B_m_s2)
