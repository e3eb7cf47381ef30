"""Open-loop recording: drive a vehicle along a scenario trajectory and write a EuRoC ASL dataset.

Steps:

1. Split the seed into independent streams (IMU, frame drops, pixel noise, landmarks) with
   ``numpy.random.SeedSequence.spawn`` so that changing one component does not shift the others.
2. Build the camera schedule (exposure on the IMU clock, stamp on the camera clock, drops/blackouts).
3. In chunks of :data:`IMU_CHUNK_SAMPLES`: sample the analytic truth at the IMU rate, pass it through the IMU
   model (bias walk, noise, ...), write the IMU and ground-truth rows, then render and write the frames
   exposed up to the chunk's end (the vehicle placed kinematically at the exposure-time truth). Memory stays
   flat however long the recording, and the files grow from the start.
4. Write the ``sensor.yaml`` files and the scene landmarks (for the simulated-feature fast mode).

Everything is written into a temporary sibling of ``out_dir`` that becomes ``out_dir`` only when the
recording is complete (:func:`viotb.envs.tools.outdir.atomic_out_dir`): an interrupted recording leaves
nothing that ``viotb eval`` would accept.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np
from viotb.envs.data.euroc_writer import EurocStreamWriter, write_true_calibration
from viotb.envs.scenarios.failures import failure_record_scenario
from viotb.envs.scenarios.motions import TimeShifted, Trajectory
from viotb.envs.scenarios.registry import get_scenario
from viotb.envs.scenarios.spec import Scenario
from viotb.envs.sim.camera_timing import frame_schedule
from viotb.envs.sim.imu_model import ImuModel
from viotb.envs.sim.imu_model import imu_preset as imu_preset_params
from viotb.envs.tools.outdir import atomic_out_dir
from viotb.models.constants import VEHICLE_BODIES
from viotb.vio.lie import rotmat_to_quat_wxyz
from viotb.vio.types import TrajectoryArrays

LANDMARK_COUNT = 3000
"""Scene landmarks written to ``sim_landmarks0`` (for the simulated-feature front end)."""
MIN_START_SPEED_M_S = 0.05
"""A start in motion (``start_at_s``) must find the vehicle at least this fast (m/s)."""
IMU_CHUNK_SAMPLES = 65536
"""IMU samples simulated and written per chunk (a multiple of the IMU model's block: same bytes per seed)."""


def record_scenario(
    name: str,
    out_dir: Path | str,
    seed: int = 0,
    seconds: float | None = None,
    progress: Callable[[float, float], None] | None = None,
    severity: float | None = None,
    imu_preset: str | None = None,
    resolution: tuple[int, int] | None = None,
    camera_rate_hz: float | None = None,
    imu_rate_hz: float | None = None,
    overwrite: bool = False,
    cameras: int | None = None,
    start_at_s: float | None = None,
) -> dict:
    """Simulate scenario ``name`` open loop and write a EuRoC ASL folder ``out_dir/mav0``.

    Args:
        name: A ``"record"`` scenario (see ``viotb scenarios``).
        out_dir: Output folder; checked before any work, refused when not empty unless ``overwrite``, and
            written atomically.
        seed: Seed of every random component (>= 0; same seed, byte-identical output).
        seconds: Duration (s); the scenario default when None.
        progress: Optional callback ``(done, total)`` called after each rendered frame.
        severity: For a ``fail-*`` scenario, its severity knob (``viotb.envs.scenarios.failures``); None =
            default.
        imu_preset: Record with this IMU preset instead of the scenario's (None: the scenario's).
        resolution: Image ``(width, height)`` in px (None: the scenario's, 320x240 by default).
        camera_rate_hz: Camera rate (Hz; None: the scenario's).
        imu_rate_hz: IMU rate (Hz; None: the preset's).
        overwrite: Replace a non-empty ``out_dir`` when the recording completes.
        cameras: Cameras to record, 1 (``cam0``) or 2 (``cam0`` and ``cam1``, a stereo rig's scenario only);
            None = every camera of the scenario's rig.
        start_at_s: Start in motion: the recording (IMU, images, ground truth) begins this long (s) into the
            scenario's trajectory (its still start included) and lasts ``seconds``; the vehicle must be
            moving there (>= :data:`MIN_START_SPEED_M_S`). None: from the start, at rest.

    Returns:
        ``{"frames", "imu_samples", "path_length_m", "seconds", "scenario", "seed", "realtime_factor",
        "out", "dropped_frames", "saturated_samples", "resolution", "camera_rate_hz", "imu_rate_hz",
        "start_at_s", "start_speed_m_s"}``.

    Raises:
        ValueError: Unknown scenario, a scenario without a scripted trajectory, a bad duration, seed, size
            or rate, or an unusable ``out_dir`` (:class:`viotb.envs.tools.outdir.OutDirError`).
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    from viotb.envs.sim.camera_rig import CameraRig
    from viotb.envs.sim.landmarks import scene_landmarks  # (imports mujoco)
    from viotb.envs.sim.render import ensure_offscreen_buffer
    from viotb.envs.sim.simulation import Simulation

    wall_start = time.perf_counter()
    if not (isinstance(seed, int | np.integer) and seed >= 0):
        raise ValueError(f"record_scenario: seed must be an integer >= 0, got {seed!r}")
    if seconds is not None and not (np.isfinite(seconds) and seconds > 0.0):
        raise ValueError(f"record_scenario: seconds must be positive, got {seconds}")
    scenario = get_scenario(name) if severity is None else failure_record_scenario(name, severity)
    if imu_preset is not None:
        scenario = replace(scenario, imu_preset=imu_preset)
    cam_params = scenario.camera
    if resolution is not None:
        cam_params = replace(cam_params, width=int(resolution[0]), height=int(resolution[1]))
    if camera_rate_hz is not None:
        cam_params = replace(cam_params, rate_hz=float(camera_rate_hz))
    imu_params = imu_preset_params(scenario.imu_preset)
    if imu_rate_hz is not None:
        imu_params = replace(imu_params, rate_hz=float(imu_rate_hz))
    duration_s = float(scenario.default_seconds if seconds is None else seconds)
    trajectory, start_speed = _trajectory(scenario, duration_s, start_at_s)
    rig_cameras = scenario.rig_cameras if cameras is None else scenario.rig_cameras[:cameras]
    if cameras is not None and (cameras not in (1, 2) or len(rig_cameras) != cameras):
        raise ValueError(
            f"record_scenario: {name!r} has {len(scenario.rig_cameras)} camera(s), asked for {cameras}"
        )

    with atomic_out_dir(out_dir, overwrite) as tmp_dir:
        # 1. Independent random streams.
        # The spawn index of a stream never changes, so cam1's noise leaves cam0's images of a seed unchanged.
        imu_seq, drop_seq, pixel_seq, landmark_seq, pixel1_seq = np.random.SeedSequence(seed).spawn(5)
        imu_model = ImuModel(imu_params, np.random.default_rng(imu_seq))
        faults = scenario.faults

        # 2. Camera schedule.
        schedule = frame_schedule(cam_params, duration_s, np.random.default_rng(drop_seq))
        kept = schedule.kept_indices

        sim = Simulation(scenario.vehicle, scenario.scene)
        ensure_offscreen_buffer(sim.model, cam_params.width, cam_params.height)
        is_headset = scenario.vehicle == "headset"
        rig = CameraRig(
            sim.model,
            rig_cameras,
            VEHICLE_BODIES[scenario.vehicle],
            cam_params,
            [np.random.default_rng(pixel_seq), np.random.default_rng(pixel1_seq)],
        )

        def place_at(t_s: float) -> None:
            s = trajectory.sample(t_s)
            sim.set_pose(s.R_WB, s.p_WB, s.v_WB, s.omega_B, a_W=s.a_WB if is_headset else None)

        # 3. IMU and ground truth in chunks, each followed by the frames exposed up to its end.
        n_imu = int(np.floor(duration_s * imu_params.rate_hz + 1e-9)) + 1
        path_length_m, saturated, next_frame, last_p = 0.0, 0, 0, None
        # A wrong calibration file when the scenario says so.
        writer = EurocStreamWriter(
            tmp_dir,
            faults.told_calibration(rig.calibs[0]),
            calib_right=faults.told_calibration(rig.calibs[1]) if len(rig) == 2 else None,
            exposure_s=cam_params.exposure_s if scenario.camera_names else None,
        )
        try:
            for start in range(0, n_imu, IMU_CHUNK_SAMPLES):
                t_imu = np.arange(start, min(start + IMU_CHUNK_SAMPLES, n_imu)) / imu_params.rate_hz
                truth = trajectory.sample_many(t_imu)
                # The scenario's IMU faults (an extra gyro bias, an accelerometer scale error) act first.
                imu, gyro_bias, accel_bias = imu_model.measure_series_with_biases(
                    t_imu, *faults.imu_input(truth.omega_B, truth.specific_force_B)
                )
                writer.imu(imu)
                quat = np.array([rotmat_to_quat_wxyz(R) for R in truth.R_WB])
                gt = TrajectoryArrays(t_imu, truth.p_WB, quat, truth.v_WB)
                writer.groundtruth(gt, gyro_bias + faults.extra_gyro_bias_rad_s, accel_bias)
                p = truth.p_WB if last_p is None else np.vstack([last_p, truth.p_WB])
                path_length_m += float(np.sum(np.linalg.norm(np.diff(p, axis=0), axis=1)))
                last_p, saturated = truth.p_WB[-1:], saturated + int(np.count_nonzero(imu.saturated))
                last_chunk = start + IMU_CHUNK_SAMPLES >= n_imu
                while next_frame < len(kept):
                    i = kept[next_frame]
                    t_exp = float(schedule.t_exposure_imu_s[i])
                    if t_exp > t_imu[-1] and not last_chunk:
                        break
                    writer.frame(float(schedule.t_stamp_cam_s[i]), *rig.render(sim.data, place_at, t_exp))
                    next_frame += 1
                    if progress is not None:
                        progress(next_frame, len(kept))
            # 4. Calibration files and landmarks.
            landmarks_W = scene_landmarks(sim.model, np.random.default_rng(landmark_seq), LANDMARK_COUNT)
            mav0 = writer.finish(imu_params.noise, imu_params.rate_hz, landmarks_W)
            # The true cam0 calibration beside the (maybe wrong) sensor.yaml, for scoring and sim features.
            write_true_calibration(mav0, rig.calibs[0])
        finally:
            writer.close()
            rig.close()
    wall_s = time.perf_counter() - wall_start
    return {
        "frames": int(len(kept)),
        "imu_samples": int(n_imu),
        "path_length_m": path_length_m,
        "seconds": duration_s,
        "scenario": name,
        "seed": int(seed),
        "realtime_factor": float(duration_s / wall_s),
        "out": str(Path(out_dir)),
        "dropped_frames": int(len(schedule) - len(kept)),
        "saturated_samples": saturated,
        "resolution": [int(cam_params.width), int(cam_params.height)],
        "camera_rate_hz": float(cam_params.rate_hz),
        "imu_rate_hz": float(imu_params.rate_hz),
        "cameras": len(rig),
        "start_at_s": float(start_at_s or 0.0),
        "start_speed_m_s": start_speed,
    }


def default_start_in_motion_s(scenario: Scenario) -> float:
    """Where ``--start-in-motion`` enters a scenario by default (s): 2 s after its still start ends.

    The motions ramp their rate up over their first 2 s, so the vehicle is there at its cruise rate: moving,
    with no rest for a static initializer.
    """
    return scenario.still_start_s + 2.0


def _trajectory(scenario: Scenario, duration_s: float, start_at_s: float | None) -> tuple[Trajectory, float]:
    """The recording's trajectory and its speed at time 0 (m/s): entered at ``start_at_s`` when given."""
    if start_at_s is None:
        trajectory = scenario.make_trajectory(duration_s)
        return trajectory, float(np.linalg.norm(trajectory.sample(0.0).v_WB))
    if not (np.isfinite(start_at_s) and start_at_s >= 0.0):
        raise ValueError(f"record_scenario: start_at_s must be >= 0 s, got {start_at_s}")
    shifted = TimeShifted(scenario.make_trajectory(start_at_s + duration_s), float(start_at_s))
    speed = float(np.linalg.norm(shifted.sample(0.0).v_WB))
    if speed < MIN_START_SPEED_M_S:
        raise ValueError(
            f"record_scenario: {scenario.name!r} at start_at_s={start_at_s} s moves at {speed:.3f} m/s "
            f"(< {MIN_START_SPEED_M_S} m/s): not a start in motion; choose a later start_at_s"
        )
    return shifted, speed
