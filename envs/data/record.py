"""Open-loop recording: drive a vehicle along a scenario trajectory and write a EuRoC ASL dataset.

Steps:

1. Split the seed into independent streams (IMU, frame drops, pixel noise, landmarks) with
   ``numpy.random.SeedSequence.spawn`` so that changing one component does not shift the others.
2. Sample the analytic truth at the IMU rate and pass it through the IMU model (bias walk, noise, ...).
3. Build the camera schedule (exposure on the IMU clock, stamp on the camera clock, drops/blackouts).
4. For each kept frame, place the vehicle kinematically at the exposure-time truth
   (:meth:`Simulation.set_pose`) and render a gray image with pixel noise.
5. Write ``mav0/`` (images streamed to disk as they are rendered), ground truth at the IMU rate with the
   true biases, and the scene landmarks (for the simulated-feature fast mode).
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc_writer import write_euroc
from viotb.envs.scenarios.failures import failure_record_scenario
from viotb.envs.scenarios.registry import get_scenario
from viotb.envs.sim.camera_timing import frame_schedule
from viotb.envs.sim.imu_model import ImuModel
from viotb.envs.sim.imu_model import imu_preset as imu_preset_params
from viotb.models.constants import ONBOARD_CAMERA, VEHICLE_BODIES
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.types import TrajectoryArrays

LANDMARK_COUNT = 3000
"""Scene landmarks written to ``sim_landmarks0`` (for the simulated-feature front end)."""


def record_scenario(
    name: str,
    out_dir: Path | str,
    seed: int = 0,
    seconds: float | None = None,
    progress: Callable[[float, float], None] | None = None,
    severity: float | None = None,
    imu_preset: str | None = None,
) -> dict:
    """Simulate scenario ``name`` open loop and write a EuRoC ASL folder ``out_dir/mav0``.

    Args:
        name: A ``"record"`` scenario (see ``viotb scenarios``).
        out_dir: Output folder (created).
        seed: Seed of every random component (same seed, byte-identical output).
        seconds: Duration (s); the scenario default when None.
        progress: Optional callback ``(done, total)`` called after each rendered frame.
        severity: For a ``fail-*`` scenario, its severity knob (``viotb.envs.scenarios.failures``); None =
            default.
        imu_preset: Record with this IMU preset instead of the scenario's (None: the scenario's).

    Returns:
        ``{"frames", "imu_samples", "path_length_m", "seconds", "scenario", "seed", "realtime_factor",
        "out", "dropped_frames", "saturated_samples"}``.

    Raises:
        ValueError: Unknown scenario, a scenario without a scripted trajectory, or a bad duration.
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    from viotb.envs.sim.landmarks import scene_landmarks  # (imports mujoco)
    from viotb.envs.sim.render import OffscreenRenderer, camera_calibration
    from viotb.envs.sim.simulation import Simulation

    wall_start = time.perf_counter()
    if severity is None:
        scenario = get_scenario(name)
    else:
        scenario = failure_record_scenario(name, severity)
    if imu_preset is not None:
        scenario = replace(scenario, imu_preset=imu_preset)
    if seconds is not None and not (np.isfinite(seconds) and seconds > 0.0):
        raise ValueError(f"record_scenario: seconds must be positive, got {seconds}")
    duration_s = float(scenario.default_seconds if seconds is None else seconds)
    trajectory = scenario.make_trajectory(duration_s)
    cam_params = scenario.camera
    imu_params = imu_preset_params(scenario.imu_preset)

    # 1. Independent random streams.
    imu_seq, drop_seq, pixel_seq, landmark_seq = np.random.SeedSequence(seed).spawn(4)

    # 2. Truth at the IMU rate -> IMU readings and the true biases.
    n_imu = int(np.floor(duration_s * imu_params.rate_hz + 1e-9)) + 1
    t_imu = np.arange(n_imu) / imu_params.rate_hz
    truth = trajectory.sample_many(t_imu)
    imu_model = ImuModel(imu_params, np.random.default_rng(imu_seq))
    # The scenario's IMU faults (an extra gyro bias, an accelerometer scale error) act before the model.
    faults = scenario.faults
    imu, gyro_bias, accel_bias = imu_model.measure_series_with_biases(
        t_imu, *faults.imu_input(truth.omega_B, truth.specific_force_B)
    )
    gyro_bias = gyro_bias + faults.extra_gyro_bias_rad_s

    # 3. Camera schedule.
    schedule = frame_schedule(cam_params, duration_s, np.random.default_rng(drop_seq))
    kept = schedule.kept_indices

    # 4. Render at the exposure instants.
    sim = Simulation(scenario.vehicle, scenario.scene)
    is_headset = scenario.vehicle == "headset"
    calib = camera_calibration(
        sim.model,
        ONBOARD_CAMERA,
        VEHICLE_BODIES[scenario.vehicle],
        cam_params.width,
        cam_params.height,
        cam_params.time_offset_s,
        cam_params.rate_hz,
    )
    renderer = OffscreenRenderer(
        sim.model,
        cam_params.width,
        cam_params.height,
        ONBOARD_CAMERA,
        pixel_noise_std=cam_params.pixel_noise_std,
        rng=np.random.default_rng(pixel_seq),
    )

    def place_at(t_s: float) -> None:
        s = trajectory.sample(t_s)
        sim.set_pose(s.R_WB, s.p_WB, s.v_WB, s.omega_B, a_W=s.a_WB if is_headset else None)

    blur_offsets_s = np.linspace(-0.5, 0.5, cam_params.blur_samples) * cam_params.exposure_s

    def frames() -> Iterator[tuple[float, np.ndarray]]:
        for done, i in enumerate(kept, start=1):
            t_exp = float(schedule.t_exposure_imu_s[i])
            if cam_params.exposure_s > 0.0:
                image = renderer.render_gray_exposure(
                    sim.data, lambda o, t=t_exp: place_at(t + o), blur_offsets_s
                )
            else:
                place_at(t_exp)
                image = renderer.render_gray(sim.data)
            yield float(schedule.t_stamp_cam_s[i]), image
            if progress is not None:
                progress(done, len(kept))

    # 5. Write everything.
    landmarks_W = scene_landmarks(sim.model, np.random.default_rng(landmark_seq), LANDMARK_COUNT)
    groundtruth = TrajectoryArrays(
        t_imu, truth.p_WB, np.array([rotmat_to_quat_wxyz(R) for R in truth.R_WB]), truth.v_WB
    )
    try:
        mav0 = write_euroc(
            out_dir,
            imu,
            frames(),
            faults.told_calibration(calib),  # a wrong calibration file when the scenario says so
            imu_params.noise,
            groundtruth,
            gyro_bias,
            accel_bias,
            landmarks_W,
            imu_rate_hz=imu_params.rate_hz,
        )
    finally:
        renderer.close()
    wall_s = time.perf_counter() - wall_start
    return {
        "frames": int(len(kept)),
        "imu_samples": int(n_imu),
        "path_length_m": float(np.sum(np.linalg.norm(np.diff(truth.p_WB, axis=0), axis=1))),
        "seconds": duration_s,
        "scenario": name,
        "seed": int(seed),
        "realtime_factor": float(duration_s / wall_s),
        "out": str(mav0.parent),
        "dropped_frames": int(len(schedule) - len(kept)),
        "saturated_samples": int(np.count_nonzero(imu.saturated)),
    }
