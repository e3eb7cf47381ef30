"""Gymnasium environments with VIO in the loop: a quadrotor policy that sees the estimate, not the truth.

Three tasks share one base class (:class:`VioQuadEnv`); each env holds only its task logic (targets, a success
test) on top of :class:`~viotb.envs.run.closed_loop.ClosedLoopSim`, which runs physics, IMU, camera and
estimator in lockstep (cf. dm_control's physics/task split and Gymnasium ``envs/mujoco/hopper_v5.py``):

* :class:`HoverEnv` (``viotb/Hover-v0``): hold a point against wind gusts.
* :class:`WaypointsEnv` (``viotb/Waypoints-v0``): fly through a random sequence of points.
* :class:`TrackEnv` (``viotb/Track-v0``): follow a moving figure-8 reference.

One policy step lasts ``ctrl_dt``; inside it the low-level loop (rate controller or SE(3) controller,
depending on ``action_type``) runs every ``inner_ctrl_dt`` on the latest estimate, and physics steps at the
model's ``sim_dt`` (mujoco_playground's ``ctrl_dt`` / ``sim_dt``, ``n_substeps = round(ctrl_dt / sim_dt)``).
Every tunable lives once in a frozen config dataclass per env (:class:`HoverEnvConfig`, ...); keyword
arguments to the constructor (and so to ``gymnasium.make``) override its fields. Rewards are sums of named
terms, one small function each, computed from ground truth (the simulator is the referee); observations come
from the estimator only.
"""

from __future__ import annotations

import math
from collections import deque

import gymnasium
import numpy as np
from gymnasium import spaces
from viotb.controllers import Mixer, SE3Controller, SE3Gains
from viotb.controllers.types import FlatOutput
from viotb.envs.gym.config import FAILURE_REASONS, RENDER_CAMERAS, VioEnvConfig, make_config
from viotb.envs.gym.info import step_info
from viotb.envs.gym.observation import orientation_features, state_vector_rot6d
from viotb.envs.gym.rewards import cost_crash, cost_effort, cost_smoothness, reward_tracking
from viotb.envs.gym.starts import ground_start, place_airborne, randomize_sensor_and_body, rig_config
from viotb.envs.run.closed_loop import ClosedLoopSim
from viotb.envs.sim.checks import all_finite, norm3
from viotb.envs.sim.simulation import Simulation
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.models.constants import CHASE_CAMERA, SCENE_BOUNDS_M
from viotb.vio.lie import cross, yaw_from_rotmat
from viotb.vio.types import StateEstimate


def _whole_multiple(value: float, unit: float, what: str) -> int:
    """``round(value / unit)``, or a ValueError when ``value`` is not a whole multiple of ``unit``."""
    n = round(value / unit)
    if n < 1 or abs(n * unit - value) > 1e-9:
        raise ValueError(f"{what} = {value} s must be a whole multiple of {unit} s")
    return n


class VioQuadEnv(gymnasium.Env):
    """Base class of the VIO-in-the-loop quadrotor tasks; subclasses define the targets (see module doc).

    ## Action Space
    ``Box(-1, 1, (4,), float32)``, meaning set by ``action_type``:

    - ``motors``: normalized motor thrusts, ``-1 -> 0 N``, ``+1 ->`` the MJCF ``ctrlrange`` maximum (8 N).
    - ``ctbr``: ``[collective, p, q, r]``: collective thrust ``(a0 + 1) / 2 * 32 N`` and body rates
      ``a[1:] * max_body_rate_rad_s``, held by a rate loop (on the estimated, bias-corrected rate) every
      ``inner_ctrl_dt``.
    - ``velocity``: ``[vx, vy, vz, yaw_rate]`` setpoint (``* max_speed_m_s``, ``* max_yaw_rate_rad_s``) in the
      estimator's world frame, through the SE(3) controller on the estimate.
    - ``position``: ``[dx, dy, dz, dyaw]``: the SE(3) controller's setpoint is the target plus
      ``a[:3] * position_range_m`` and the initial yaw plus ``a[3] * pi``.

    Actions outside ``[-1, 1]`` are clipped; a wrong shape or NaN raises ``ValueError``.

    ## Observation Space
    ``obs_mode="state"``: a float32 Box; every entry comes from the ESTIMATOR (names in
    ``env.unwrapped.state_names()``): estimated position minus target (3), estimated velocity (3),
    estimated orientation (``rot6d``: 6, or ``quat_wxyz``: 4), bias-corrected angular rate (3), target
    position (3) and velocity (3) in the estimator's frame, estimator position and velocity covariance
    diagonals (3 + 3) and the tracked-feature count (1). ``obs_mode="dict"`` adds ``image`` (the last onboard
    gray frame, (H, W, 1) uint8) and ``imu`` (the last ``imu_window`` raw IMU samples, gyro then
    accelerometer, (K, 6)). Ground truth is only in ``info`` (``p_true_W_m``, ``v_true_W_m_s``,
    ``R_true_WB``, ``position_error_m``, ``estimate_error_m``; ``info="flat"`` keeps only the scalars, the
    cheap form for vector envs: :mod:`viotb.envs.gym.info`).

    ## Rewards Sum of ``info["reward_components"]`` (also ``info["reward_<name>"]``), computed from the TRUE
    position: ``tracking = w * exp(-|p - p_target| / tracking_scale_m)``, ``effort = -w |a - a_hover|^2``,
    ``smoothness = -w |a_k - a_(k-1)|^2``, ``crash = -w`` on a failed episode (Waypoints adds ``waypoint = w``
    per point reached).

    ## Starting State
    ``start="air"`` (default): the body starts at ``start_p_W_m`` plus N(0, 0.1 m) per axis, with a velocity
    of N(0, 0.1 m/s), roll/pitch N(0, 0.05 rad) and yaw N(0, 0.1 rad). The estimator does NOT run its own
    initialization: it is initialized from the truth perturbed by N(0, ``init_*_sigma``) (attitude, position,
    velocity, both biases), with exactly those sigmas as its prior covariance; the ``ground-truth``
    estimator gets the truth. ``start="ground"``: the body sits on the floor below ``start_p_W_m``, the
    estimator initializes as on a real drone (up to ``ground_init_max_s``), and an SE(3) takeoff on the
    estimate climbs to the start point inside ``reset`` (slow; task targets are mapped into the estimator's
    frame through the known launch pad). Domain randomization (IMU noise/bias scale, mass, wind) is drawn at
    reset from ``env.np_random``, which only ``reset(seed=...)`` seeds.

    ## Episode End Terminated on a crash (contact, tilt over 80 deg), leaving the arena (the scene's free
    space shrunk by ``arena_margin_m``), being farther than ``max_target_distance_m`` from the target, or
    estimator divergence (``health.diverged``) (Waypoints: or success after the last point, without penalty);
    ``info["termination_reason"]`` says which. Truncation: only by the ``TimeLimit`` of the registration
    (``max_episode_steps``; override it in ``gymnasium.make``).

    ## Arguments ``render_mode`` (``None`` or ``"rgb_array"``: the ``chase`` camera, or
    ``render_camera="onboard"``; ``env.unwrapped.render_camera(name)`` renders either), ``config`` (the task's
    config class: ``HoverEnvConfig``, ...), and any field of it as a keyword (``action_type``, ``estimator``,
    ``frontend``, ``imu_preset``, ``camera_width``, ``camera_height``, ``ctrl_dt``, ``randomization``,
    ``obs_mode``, ...). Unknown names or values raise ``ValueError`` listing the allowed ones.

    ## Version History
    - v0: initial version.

    ## Subclassing

    Subclasses set :attr:`config_type` and implement :meth:`_task_reset`, :meth:`_target_W` and may
    override :meth:`_task_step`.

    Args:
        render_mode: ``None`` or ``"rgb_array"``.
        config: Full configuration; the defaults of :attr:`config_type` when None.
        **overrides: Fields of the config to override (e.g. ``action_type="ctbr"``).

    Raises:
        ValueError: Unknown keyword or value (listing the allowed ones), periods that do not divide.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}
    """``render_fps`` = 1 / the default ``ctrl_dt`` (one frame per step)."""
    config_type: type[VioEnvConfig] = VioEnvConfig

    def __init__(
        self, render_mode: str | None = None, config: VioEnvConfig | None = None, **overrides
    ) -> None:
        """Validate the configuration, read the vehicle from the MJCF and build the spaces."""
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"unknown render_mode {render_mode!r}; allowed: None, 'rgb_array'")
        cfg = make_config(self.config_type, config, overrides)
        self.config = cfg
        self.render_mode = render_mode
        nominal = Simulation("quadrotor", cfg.scene)
        self.sim_dt = nominal.timestep_s
        self.n_substeps = _whole_multiple(cfg.ctrl_dt, self.sim_dt, "ctrl_dt")
        self._n_inner = _whole_multiple(cfg.ctrl_dt, cfg.inner_ctrl_dt, "ctrl_dt")
        _whole_multiple(cfg.inner_ctrl_dt, self.sim_dt, "inner_ctrl_dt")
        self._vehicle = vehicle_params_from_model(nominal.model)
        self._mixer = Mixer(self._vehicle)
        self._neutral = self._neutral_action()
        lo, hi = SCENE_BOUNDS_M[cfg.scene]
        # The arena box as float triples (the per-step test compares floats, not arrays).
        self._arena_lo = tuple((np.asarray(lo) + cfg.arena_margin_m).tolist())
        self._arena_hi = tuple((np.asarray(hi) - cfg.arena_margin_m).tolist())
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.observation_space = self._observation_space()
        state_space = self.observation_space if cfg.obs_mode == "state" else self.observation_space["state"]
        self._state_low, self._state_high = state_space.low, state_space.high  # read every step
        self._loop: ClosedLoopSim | None = None
        self._controller: SE3Controller | None = None
        self._renderer = None
        self._imu: deque = deque(maxlen=cfg.imu_window)
        self._setpoint_cache: tuple[tuple, FlatOutput] | None = None
        self._target_key: tuple | None = None
        self._terminated = False

    @property
    def rig(self) -> ClosedLoopSim | None:
        """The current episode's closed-loop rig (simulation, sensors, estimator), for diagnostics."""
        return self._loop

    @property
    def dt(self) -> float:
        """Policy step (s) = ``ctrl_dt``."""
        return self.config.ctrl_dt

    # ------------------------------------------------------------------ spaces

    def _state_layout(self) -> list[tuple[str, int, float, float]]:
        """(name, size, low, high) of each entry of the flat state vector, in order."""
        n_ori = 6 if self.config.orientation == "rot6d" else 4
        inf = np.inf
        return [
            ("p_rel_W_m", 3, -inf, inf),  # estimated position minus target (estimator frame)
            ("v_W_m_s", 3, -inf, inf),  # estimated velocity
            ("orientation", n_ori, -1.0, 1.0),  # estimated attitude
            ("omega_B_rad_s", 3, -inf, inf),  # bias-corrected gyro rate
            ("target_p_W_m", 3, -inf, inf),  # target position (estimator frame)
            ("target_v_W_m_s", 3, -inf, inf),  # target velocity
            ("var_p_m2", 3, 0.0, inf),  # estimator position covariance diagonal
            ("var_v_m2_s2", 3, 0.0, inf),  # estimator velocity covariance diagonal
            ("tracked_features", 1, 0.0, inf),
        ]

    def _observation_space(self) -> spaces.Space:
        layout = self._state_layout()
        low = np.concatenate([np.full(n, lo) for _, n, lo, _ in layout]).astype(np.float32)
        high = np.concatenate([np.full(n, hi) for _, n, _, hi in layout]).astype(np.float32)
        state = spaces.Box(low, high, dtype=np.float32)
        if self.config.obs_mode == "state":
            return state
        cfg = self.config
        return spaces.Dict(
            {
                "state": state,
                "image": spaces.Box(0, 255, shape=(cfg.camera_height, cfg.camera_width, 1), dtype=np.uint8),
                "imu": spaces.Box(-np.inf, np.inf, shape=(cfg.imu_window, 6), dtype=np.float32),
            }
        )

    def state_names(self) -> list[str]:
        """Names of the entries of the flat state vector (e.g. ``p_rel_W_m[0]``), in order."""
        return [f"{name}[{i}]" for name, n, _, _ in self._state_layout() for i in range(n)]

    # ------------------------------------------------------------------ task hooks

    def _task_reset(self, rng: np.random.Generator) -> None:
        """Draw the task's random elements (waypoints...) at the start of an episode."""

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        """Target position (m) and velocity (m/s) in the world frame at task time ``t_s``."""
        raise NotImplementedError

    def _task_step(self, p_true_W: np.ndarray) -> tuple[dict[str, float], bool]:
        """Task-specific reward terms and success flag after a step (true position, m)."""
        return {}, False

    # ------------------------------------------------------------------ actions

    def _neutral_action(self) -> np.ndarray:
        """The action that holds a hover (reference of the effort cost)."""
        v = self._vehicle
        if self.config.action_type == "motors":
            per_motor = v.hover_thrust_N / 4.0
            return (2.0 * (per_motor - v.min_thrust_N) / (v.max_thrust_N - v.min_thrust_N) - 1.0).astype(
                float
            )
        if self.config.action_type == "ctbr":
            return np.array([2.0 * v.hover_thrust_N / float(np.sum(v.max_thrust_N)) - 1.0, 0.0, 0.0, 0.0])
        return np.zeros(4)

    def _check_action(self, action: object) -> np.ndarray:
        a = np.asarray(action, dtype=float)
        if a.shape != (4,):
            raise ValueError(
                f"action must have shape (4,) for action_type {self.config.action_type!r}, got {a.shape}"
            )
        values = a.tolist()
        if not all_finite(values):
            raise ValueError(f"action must be finite, got {values}")
        # a.clip(-1, 1) entry by entry (the same values, -0.0 kept), without numpy's clip call.
        return np.array([-1.0 if x < -1.0 else 1.0 if x > 1.0 else x for x in values])

    def _thrusts(self, a: np.ndarray, est: StateEstimate) -> np.ndarray:
        """Motor thrusts (N) for action ``a`` on the estimate ``est`` (one low-level tick)."""
        cfg, v = self.config, self._vehicle
        if cfg.action_type == "motors":
            return v.min_thrust_N + 0.5 * (a + 1.0) * (v.max_thrust_N - v.min_thrust_N)
        if cfg.action_type == "ctbr":
            # Collective thrust (N); proportional rate loop with gyroscopic compensation, on the estimate.
            collective = 0.5 * (a[0] + 1.0) * float(np.sum(v.max_thrust_N))
            omega_cmd = a[1:] * np.asarray(cfg.max_body_rate_rad_s)
            w = est.omega_B_rad_s
            J = v.inertia_kg_m2
            moments = J @ (np.asarray(cfg.rate_bandwidth_rad_s) * (omega_cmd - w)) + cross(w, J @ w)
            return self._mixer.motor_thrusts(collective, moments)
        if cfg.action_type == "velocity":
            self._yaw_setpoint += a[3] * cfg.max_yaw_rate_rad_s * cfg.inner_ctrl_dt
            setpoint = FlatOutput(
                p_W=est.p_WB,
                v_W=a[:3] * cfg.max_speed_m_s,
                yaw_rad=self._yaw_setpoint,
                yaw_rate_rad_s=a[3] * cfg.max_yaw_rate_rad_s,
            )
        else:
            setpoint = self._position_setpoint(a)
        return self._controller.thrusts_from_estimate(self._loop.t_s, est, setpoint)

    def _position_setpoint(self, a: np.ndarray) -> FlatOutput:
        """Setpoint of the ``position`` action: constant over a policy step, so built once per step.

        Cached on the action and the target (both fixed during a step); the validated record is reused by
        the step's ``ctrl_dt / inner_ctrl_dt`` low-level ticks instead of being rebuilt at each.
        """
        key = (a.tobytes(), self._target_est.tobytes(), self._yaw0)
        if self._setpoint_cache is None or self._setpoint_cache[0] != key:
            p_W = (self._target_est + a[:3] * self.config.position_range_m).tolist()
            zero = [0.0, 0.0, 0.0]
            setpoint = FlatOutput.from_floats(p_W, zero, zero, zero, self._yaw0 + a[3] * np.pi, 0.0)
            self._setpoint_cache = (key, setpoint)
        return self._setpoint_cache[1]

    # ------------------------------------------------------------------ reset

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode (see the class docstring's Starting State); seeding only through ``seed``."""
        super().reset(seed=seed)
        rng = self.np_random
        cfg = self.config
        self.close_loop()
        rig_seed = int(rng.integers(0, 2**31 - 1))
        loop = ClosedLoopSim(rig_config(cfg, rng), seed=rig_seed)
        self._loop = loop
        randomize_sensor_and_body(loop, cfg, rng)
        self._R_EW, self._t_EW = np.eye(3), np.zeros(3)
        self._target_key = None  # the estimator frame is new: recompute the target in it
        if cfg.start == "air":
            place_airborne(loop, cfg, rng)
        else:
            self._R_EW, self._t_EW = ground_start(loop, cfg, self._vehicle)
        self._task_reset(rng)
        self._controller = SE3Controller(self._vehicle, SE3Gains())
        est = loop.estimate()
        self._yaw0 = yaw_from_rotmat(est.R_WB) if est is not None else 0.0
        self._yaw_setpoint = self._yaw0
        self._t_task = 0.0
        self._prev_action = self._neutral.copy()
        self._imu.clear()
        self._terminated = False
        loop.simulate_imu = self._reads_imu()
        self._collect_imu()
        self._update_target()
        return self._get_obs(), self._get_info({}, "")

    # ------------------------------------------------------------------ step

    def _reads_imu(self) -> bool:
        """Whether anything reads the IMU samples after reset (else the rig skips the IMU model).

        The estimator does (every one but the ``ground-truth`` pass-through, which ignores them), and so does
        the ``dict`` observation's ``imu`` window; skipping changes no observation, reward or termination.
        """
        return self.config.estimator != "ground-truth" or self.config.obs_mode != "state"

    def _collect_imu(self) -> None:
        imu = self._loop.last_imu
        if imu is not None and (not self._imu or self._imu[-1].t_s != imu.t_s):
            self._imu.append(imu)

    def _update_target(self) -> None:
        """Target now, in the world (reward) and estimator (observation) frames.

        The estimator-frame target is recomputed only when the world target changes (Hover's never does;
        the values are the same, memoized on the target's bytes).
        """
        p, v = self._target_W(self._t_task)
        self._target_true_W, self._target_v_W = p, v
        key = (p.tobytes(), v.tobytes())
        if key != self._target_key:
            self._target_key = key
            self._target_est = self._R_EW @ p + self._t_EW
            self._target_v_est = self._R_EW @ v

    def _outside_arena(self, p_W: np.ndarray) -> bool:
        """Whether a true position (m), shape (3,), is outside the arena box (float comparisons)."""
        p0, p1, p2 = p_W.tolist()
        lo0, lo1, lo2 = self._arena_lo
        hi0, hi1, hi2 = self._arena_hi
        return p0 < lo0 or p1 < lo1 or p2 < lo2 or p0 > hi0 or p1 > hi1 or p2 > hi2

    def step(self, action):
        """Hold ``action`` for ``ctrl_dt``; returns ``(obs, reward, terminated, truncated, info)``."""
        if self._loop is None:
            raise RuntimeError("call reset() before step()")
        if self._terminated:
            raise RuntimeError(
                "step() after the episode terminated: call reset() first (Gymnasium's contract)"
            )
        a = self._check_action(action)
        loop = self._loop
        reason = ""
        for _ in range(self._n_inner):
            est = loop.estimate()
            if est is None or loop.health().diverged or not all(map(math.isfinite, est.p_WB.tolist())):
                reason = "diverged"
                break
            loop.advance(self._thrusts(a, est), self.config.inner_ctrl_dt)
            self._collect_imu()
            if loop.crashed(airborne=True):
                reason = "crashed"
                break
        self._t_task += self.config.ctrl_dt
        self._update_target()
        tr = loop.truth()
        if not reason and loop.health().diverged:
            reason = "diverged"
        if not reason and self._outside_arena(tr.p_WB):
            reason = "left_arena"
        err = norm3(tr.p_WB - self._target_true_W)
        if not reason and err > self.config.max_target_distance_m:
            reason = "too_far"
        task_terms, success = self._task_step(tr.p_WB)
        if not reason and success:
            reason = "success"
        self._update_target()  # the task may have switched targets
        w = self.config.rewards
        components = {
            "tracking": reward_tracking(err, w.tracking, w.tracking_scale_m),
            "effort": cost_effort(a, self._neutral, w.effort),
            "smoothness": cost_smoothness(a, self._prev_action, w.smoothness),
            "crash": cost_crash(reason in FAILURE_REASONS, w.crash),
            **task_terms,
        }
        self._prev_action = a
        reward = float(sum(components.values()))
        # Truncation is left to the TimeLimit wrapper set at registration.
        self._terminated = bool(reason)
        return self._get_obs(), reward, bool(reason), False, self._get_info(components, reason)

    # ------------------------------------------------------------------ observation and info

    def _state_vector(self) -> np.ndarray:
        est = self._loop.estimate()
        health = self._loop.health()
        if est is not None and self.config.orientation == "rot6d":
            return state_vector_rot6d(
                est,
                health.tracked_features,
                self._target_est,
                self._target_v_est,
                self._state_low,
                self._state_high,
            )
        if est is None:
            parts = [np.zeros(n) for _, n, _, _ in self._state_layout()]
        else:
            var = est.cov.diagonal()
            parts = [
                est.p_WB - self._target_est,
                est.v_WB,
                orientation_features(est.R_WB, self.config.orientation),
                est.omega_B_rad_s,
                self._target_est,
                self._target_v_est,
                var[3:6],
                var[6:9],
                [float(health.tracked_features)],
            ]
        vec = np.concatenate(parts, dtype=np.float32)
        if not np.isfinite(vec).all():  # rare: skip nan_to_num's own pass when every entry is finite
            vec = np.nan_to_num(vec, nan=0.0, posinf=1e6, neginf=-1e6)
        return np.minimum(np.maximum(vec, self._state_low, out=vec), self._state_high, out=vec)

    def _get_obs(self):
        state = self._state_vector()
        if self.config.obs_mode == "state":
            return state
        cfg = self.config
        frame = self._loop.last_frame
        image = np.zeros((cfg.camera_height, cfg.camera_width, 1), dtype=np.uint8)
        if frame is not None and frame.image is not None:
            image = frame.image[:, :, None].astype(np.uint8)
        imu = np.zeros((cfg.imu_window, 6), dtype=np.float32)
        samples = list(self._imu)
        if samples:
            rows = np.array(
                [np.concatenate([s.gyro_B_rad_s, s.accel_B_m_s2]) for s in samples], dtype=np.float32
            )
            imu[-len(rows) :] = rows
        return {"state": state, "image": image, "imu": imu}

    def _get_info(self, components: dict[str, float], reason: str) -> dict:
        """Ground truth and diagnostics (never part of the observation; ``config.info``'s form)."""
        return step_info(
            self._loop, self._target_true_W, self._R_EW, self._t_EW, components, reason, self.config.info
        )

    # ------------------------------------------------------------------ render and close

    def render(self):
        """RGB uint8 image (H, W, 3) of ``config.render_camera``; ``None`` without ``render_mode``."""
        if self.render_mode is None:
            gymnasium.logger.warn("render() called without render_mode='rgb_array'")
            return None
        return self.render_camera(self.config.render_camera)

    def render_camera(self, camera: str = CHASE_CAMERA) -> np.ndarray:
        """RGB uint8 image (H, W, 3) of a named camera (``chase`` or ``onboard``) at the current state."""
        if camera not in RENDER_CAMERAS:
            raise ValueError(f"unknown camera {camera!r}; allowed: {', '.join(map(repr, RENDER_CAMERAS))}")
        if self._loop is None:
            raise RuntimeError("call reset() before render()")
        if self._renderer is None:
            from viotb.envs.sim.render import OffscreenRenderer

            self._renderer = OffscreenRenderer(
                self._loop.sim.model, self.config.render_width, self.config.render_height, camera
            )
        return self._renderer.render_rgb(self._loop.sim.data, camera=camera)

    def close_loop(self) -> None:
        """Release the current episode's simulation and renderer (each episode builds its own)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        if self._loop is not None:
            self._loop.close()
            self._loop = None

    def close(self) -> None:
        """Release GL contexts."""
        self.close_loop()
