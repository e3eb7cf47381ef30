"""How a Gymnasium episode starts: its rig, perturbed sensors and body, and an airborne or ground start.

The rig is drawn from the randomization; an airborne start initializes the estimator from perturbed truth, a
ground start flies the takeoff of ``viotb fly`` on the estimate.
"""

from __future__ import annotations

import dataclasses

import mujoco
import numpy as np
from viotb.controllers import SE3Controller, SE3Gains
from viotb.controllers.types import NavState
from viotb.controllers.vehicle import VehicleParams
from viotb.envs.gym.config import VioEnvConfig
from viotb.envs.run.closed_loop import ClosedLoopSim
from viotb.envs.run.mission import TakeoffSequence
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.sim.imu_model import ImuModel, imu_preset
from viotb.envs.sim.rig import RigConfig, WindParams
from viotb.models.constants import QUAD_BODY
from viotb.vio.initialization import InitResult
from viotb.vio.lie import exp_so3, rotz, yaw_from_rotmat
from viotb.vio.types import StateEstimate


def uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    """One uniform draw in ``[low, high]`` (exactly ``low`` without a draw when the range is empty)."""
    lo, hi = lo_hi
    return float(lo) if hi == lo else float(rng.uniform(lo, hi))


def rig_config(cfg: VioEnvConfig, rng: np.random.Generator) -> RigConfig:
    """The episode's rig, with the wind drawn from the randomization ranges."""
    dr = cfg.randomization
    wind_mag = uniform(rng, dr.wind_mean_N)
    wind_dir = rng.uniform(0.0, 2.0 * np.pi) if wind_mag > 0.0 else 0.0
    wind = WindParams(
        mean_force_W_N=(wind_mag * np.cos(wind_dir), wind_mag * np.sin(wind_dir), 0.0),
        gust_sigma_N=uniform(rng, dr.wind_gust_sigma_N),
        gust_time_constant_s=dr.wind_gust_time_constant_s,
    )
    start = np.asarray(cfg.start_p_W_m, dtype=float)
    return RigConfig(
        scene=cfg.scene,
        estimator=cfg.estimator,
        frontend=cfg.frontend,
        imu_preset=cfg.imu_preset,
        camera=CameraModelParams(
            rate_hz=cfg.camera_rate_hz, width=cfg.camera_width, height=cfg.camera_height
        ),
        start_p_W_m=(float(start[0]), float(start[1]), 0.06),
        wind=wind,
        render_images=cfg.obs_mode == "dict",
    )


def randomize_sensor_and_body(loop: ClosedLoopSim, cfg: VioEnvConfig, rng: np.random.Generator) -> None:
    """Scale the true IMU's noise/bias and the body's mass/inertia (estimator: nominal)."""
    dr = cfg.randomization
    noise_scale, bias_scale = uniform(rng, dr.imu_noise_scale), uniform(rng, dr.imu_bias_scale)
    if noise_scale != 1.0 or bias_scale != 1.0:
        p = imu_preset(cfg.imu_preset)
        n = p.noise
        noise = dataclasses.replace(
            n,
            **{f.name: getattr(n, f.name) * noise_scale for f in dataclasses.fields(n)},
        )
        params = dataclasses.replace(
            p,
            noise=noise,
            gyro_turn_on_bias_sigma_rad_s=p.gyro_turn_on_bias_sigma_rad_s * bias_scale,
            accel_turn_on_bias_sigma_m_s2=p.accel_turn_on_bias_sigma_m_s2 * bias_scale,
        )
        loop.imu_model = ImuModel(params, rng.spawn(1)[0])
    mass_scale = uniform(rng, dr.mass_scale)
    if mass_scale != 1.0:
        model = loop.sim.model
        body = model.body(QUAD_BODY).id
        model.body_mass[body] *= mass_scale
        model.body_inertia[body] *= mass_scale
        mujoco.mj_setConst(model, loop.sim.data)
        loop.sim.model_changed()


def place_airborne(loop: ClosedLoopSim, cfg: VioEnvConfig, rng: np.random.Generator) -> None:
    """Put the body at a perturbed start pose and initialize the estimator from perturbed truth."""
    tilt = np.array([*rng.normal(0.0, cfg.start_tilt_sigma_rad, 2), 0.0])
    R_WB = rotz(rng.normal(0.0, cfg.start_yaw_sigma_rad)) @ exp_so3(tilt)
    p_WB = np.asarray(cfg.start_p_W_m, dtype=float) + rng.normal(0.0, cfg.start_position_sigma_m, 3)
    v_WB = rng.normal(0.0, cfg.start_velocity_sigma_m_s, 3)
    loop.sim.set_pose(R_WB, p_WB, v_WB)
    tr = loop.truth()
    if cfg.estimator == "ground-truth":
        loop.estimator.feed_truth(
            StateEstimate(t_s=tr.t_s, R_WB=tr.R_WB, p_WB=tr.p_WB, v_WB=tr.v_WB, omega_B_rad_s=tr.omega_B)
        )
        return
    sig = np.array(
        [
            cfg.init_attitude_sigma_rad,
            cfg.init_position_sigma_m,
            cfg.init_velocity_sigma_m_s,
            cfg.init_gyro_bias_sigma_rad_s,
            cfg.init_accel_bias_sigma_m_s2,
        ]
    )
    sig = np.maximum(sig, 1e-6)  # a zero sigma would make the filter's prior singular
    d = rng.normal(0.0, 1.0, (5, 3)) * sig[:, None]
    loop.estimator.initialize(
        InitResult(
            t_s=tr.t_s,
            R_WB=tr.R_WB @ exp_so3(d[0]),
            p_WB=tr.p_WB + d[1],
            v_WB=tr.v_WB + d[2],
            gyro_bias_rad_s=loop.imu_model.gyro_bias_rad_s + d[3],
            accel_bias_m_s2=loop.imu_model.accel_bias_m_s2 + d[4],
            method="perturbed-truth",
            cov_diag=np.repeat(sig**2, 3),
        )
    )


def ground_start(
    loop: ClosedLoopSim, cfg: VioEnvConfig, vehicle: VehicleParams
) -> tuple[np.ndarray, np.ndarray]:
    """Wait on the ground for the estimator, then take off to the start point on the estimate.

    The takeoff is :class:`~viotb.envs.run.mission.TakeoffSequence` (the one ``viotb fly`` flies), held
    for ``takeoff_s + 1`` s. The start point is mapped into the estimator's frame through the known launch
    pad (``start_p_W_m`` projected on the floor, yaw 0), not through the truth.

    Returns:
        ``(R_EW, t_EW)``: the world-to-estimator frame transform fixed by the launch pad.

    Raises:
        RuntimeError: The estimator did not initialize within ``ground_init_max_s``.
    """
    while loop.estimate() is None:
        if loop.t_s >= cfg.ground_init_max_s or loop.health().diverged:
            raise RuntimeError(
                f"estimator {cfg.estimator!r} did not initialize on the ground within "
                f"{cfg.ground_init_max_s} s (health: {loop.health()})"
            )
        loop.advance(np.zeros(4), cfg.ctrl_dt)
    pad_W = np.array(loop.config.start_p_W_m, dtype=float)
    start_W = np.asarray(cfg.start_p_W_m, dtype=float)
    frame: dict[str, np.ndarray] = {}

    def start_in_estimator_frame(est: StateEstimate) -> np.ndarray:
        frame["R_EW"] = rotz(yaw_from_rotmat(est.R_WB) - loop.config.start_yaw_rad)
        frame["t_EW"] = est.p_WB - frame["R_EW"] @ pad_W
        return frame["R_EW"] @ start_W + frame["t_EW"]

    seq = TakeoffSequence(start_in_estimator_frame, takeoff_s=cfg.takeoff_s)
    controller = SE3Controller(vehicle, SE3Gains())
    t0 = loop.t_s
    while loop.t_s - t0 < cfg.takeoff_s + 1.0:
        est = loop.estimate()
        setpoint = seq.update(loop.t_s, est, loop.estimator)
        if loop.health().diverged:
            break
        cmd = controller.update(loop.t_s, NavState.from_estimate(est), setpoint)
        loop.advance(cmd.thrusts_N, cfg.inner_ctrl_dt)
    return frame["R_EW"], frame["t_EW"]
