"""Gymnasium environments with VIO in the loop: a quadrotor policy that sees the estimate, not the truth.

Three tasks share one base class (:class:`VioQuadEnv`); each env holds only its task logic (targets, a
success test) on top of :class:`~viotb.envs.run.closed_loop.ClosedLoopSim`, which runs physics, IMU, camera and
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

import dataclasses
from collections import deque
from dataclasses import dataclass, field

import gymnasium
import mujoco
import numpy as np
from gymnasium import spaces
from viotb.controllers import FigureEight, Mixer, SE3Controller, SE3Gains, Takeoff
from viotb.controllers.types import FlatOutput, NavState
from viotb.envs.sim.camera_timing import CameraModelParams
from viotb.envs.run.closed_loop import ClosedLoopSim, RigConfig, WindParams
from viotb.envs.sim.imu_model import ImuModel, imu_preset, imu_preset_names
from viotb.envs.sim.simulation import Simulation
from viotb.envs.sim.vehicle import vehicle_params_from_model
from viotb.models.constants import CHASE_CAMERA, ONBOARD_CAMERA, QUAD_BODY, SCENE_BOUNDS_M
from viotb.vio.factory import ESTIMATOR_NAMES, FRONTEND_NAMES
from viotb.vio.initialization import InitResult
from viotb.vio.lie import cross, exp_so3, rotmat_to_quat_wxyz, rotz, yaw_from_rotmat
from viotb.vio.types import StateEstimate

ACTION_TYPES = ("motors", "ctbr", "velocity", "position")
"""``motors``: normalized thrusts; ``ctbr``: collective thrust + body rates; ``velocity`` / ``position``:
setpoints through the SE(3) controller."""
OBS_MODES = ("state", "dict")
"""``state``: one flat Box; ``dict``: ``{"state", "image", "imu"}``."""
ORIENTATIONS = ("rot6d", "quat")
STARTS = ("air", "ground")
RENDER_CAMERAS = (CHASE_CAMERA, ONBOARD_CAMERA)
FAILURE_REASONS = ("crashed", "left_arena", "too_far", "diverged")
"""Termination reasons that cost the crash penalty (``success`` does not)."""


# ---------------------------------------------------------------------------------------------- configs


@dataclass(frozen=True)
class DomainRandomization:
    """Per-episode randomization ranges ``(low, high)``, drawn uniformly from ``env.np_random`` at reset.

    The estimator and the low-level controllers keep the nominal values (IMU densities, mass): the mismatch
    is the point of randomizing.

    Attributes:
        imu_noise_scale: Factor on the IMU's white-noise and random-walk densities (true sensor only).
        imu_bias_scale: Factor on the IMU's turn-on bias sigmas (true sensor only).
        mass_scale: Factor on the body's mass and inertia (MJCF values are the nominal ones).
        wind_mean_N: Magnitude (N) of a constant horizontal wind force with a uniform random direction.
        wind_gust_sigma_N: Stationary sigma (N) of the horizontal gust force (Ornstein-Uhlenbeck).
        wind_gust_time_constant_s: Correlation time of the gusts (s), not randomized.
    """

    imu_noise_scale: tuple[float, float] = (1.0, 1.0)
    imu_bias_scale: tuple[float, float] = (1.0, 1.0)
    mass_scale: tuple[float, float] = (1.0, 1.0)
    wind_mean_N: tuple[float, float] = (0.0, 0.0)
    wind_gust_sigma_N: tuple[float, float] = (0.0, 0.0)
    wind_gust_time_constant_s: float = 1.0

    def __post_init__(self) -> None:
        """Validate each range: two finite values, low <= high, non-negative."""
        for f in dataclasses.fields(self):
            if f.name == "wind_gust_time_constant_s":
                continue
            value = getattr(self, f.name)
            lo_hi = np.asarray(value, dtype=float)
            if lo_hi.shape != (2,) or not np.all(np.isfinite(lo_hi)) or lo_hi[0] > lo_hi[1] or lo_hi[0] < 0:
                raise ValueError(
                    f"DomainRandomization.{f.name} must be (low, high) with 0 <= low <= high, got {value!r}"
                )
        if not self.wind_gust_time_constant_s > 0.0:
            raise ValueError(
                "DomainRandomization.wind_gust_time_constant_s must be > 0, got "
                f"{self.wind_gust_time_constant_s}"
            )


@dataclass(frozen=True)
class RewardWeights:
    """Weights of the reward terms (see :func:`reward_tracking` and the cost functions).

    Attributes:
        tracking: Weight of the tracking reward ``exp(-|e_p| / tracking_scale_m)`` (per step).
        tracking_scale_m: Length scale (m) of the tracking reward.
        effort: Weight of the control-effort cost ``|a - a_hover|^2``.
        smoothness: Weight of the smoothness cost ``|a_k - a_{k-1}|^2``.
        crash: Penalty for a failed episode (crash, leaving the arena, estimator divergence).
        waypoint: Bonus per waypoint reached (Waypoints task).
    """

    tracking: float = 1.0
    tracking_scale_m: float = 0.5
    effort: float = 0.05
    smoothness: float = 0.05
    crash: float = 10.0
    waypoint: float = 5.0


@dataclass(frozen=True)
class VioEnvConfig:
    """Settings shared by every VIO-in-the-loop env (units in the names).

    Attributes:
        action_type: One of :data:`ACTION_TYPES`.
        estimator: One of ``viotb.vio.factory.ESTIMATOR_NAMES`` (``msckf``, ``window``, ``imu-only``,
            ``ground-truth``).
        frontend: ``sim`` (projected landmarks, fast) or ``klt`` (OpenCV on rendered images).
        imu_preset: IMU model preset (``viotb.envs.sim.imu_model.imu_preset_names()``).
        scene: Scene name (``viotb.models.constants.SCENE_XMLS``).
        camera_width: Onboard image width (px).
        camera_height: Onboard image height (px).
        camera_rate_hz: Onboard camera rate (Hz).
        ctrl_dt: Policy step (s); a whole multiple of ``inner_ctrl_dt``.
        inner_ctrl_dt: Period of the low-level controller (s); a whole multiple of the physics step. The
            default equals the IMU period, so the ``imu`` observation sees every sample.
        start: ``air`` (airborne at the start point, estimator initialized from perturbed truth) or
            ``ground`` (on the floor below it: estimator initialization and a takeoff run inside ``reset``).
        obs_mode: One of :data:`OBS_MODES`.
        orientation: ``rot6d`` (first two columns of ``R_WB``) or ``quat`` (``quat_wxyz``, w >= 0).
        imu_window: Number of recent IMU samples in the ``imu`` entry of the dict observation.
        start_p_W_m: Start point (m); the hover point of Hover, the first point of the other tasks.
        start_position_sigma_m: Sigma of the true start position around ``start_p_W_m`` (m, per axis).
        start_velocity_sigma_m_s: Sigma of the true start velocity (m/s, per axis).
        start_tilt_sigma_rad: Sigma of the true start roll and pitch (rad).
        start_yaw_sigma_rad: Sigma of the true start yaw (rad).
        init_attitude_sigma_rad: Sigma of the estimator's initial attitude error (rad, per axis).
        init_position_sigma_m: Sigma of its initial position error (m, per axis).
        init_velocity_sigma_m_s: Sigma of its initial velocity error (m/s, per axis).
        init_gyro_bias_sigma_rad_s: Sigma of its initial gyro bias error (rad/s, per axis).
        init_accel_bias_sigma_m_s2: Sigma of its initial accelerometer bias error (m/s^2, per axis).
        ground_init_max_s: Longest wait for the estimator to initialize on the ground (s, ``start="ground"``).
        takeoff_s: Duration of the takeoff to the start point (s, ``start="ground"``).
        arena_margin_m: Margin (m) inside the scene's free space; leaving it ends the episode.
        max_target_distance_m: Distance from the target (m) beyond which the episode ends.
        max_body_rate_rad_s: Body rates at ``|a| = 1`` of the ``ctbr`` action (rad/s), (roll, pitch, yaw).
        rate_bandwidth_rad_s: Bandwidth of the ``ctbr`` rate loop (1/s) per axis.
        max_speed_m_s: Speed at ``|a| = 1`` of the ``velocity`` action (m/s).
        max_yaw_rate_rad_s: Yaw rate at ``|a| = 1`` of the ``velocity`` action (rad/s).
        position_range_m: Offset from the target at ``|a| = 1`` of the ``position`` action (m).
        render_camera: Camera of ``render()``: ``chase`` (third person) or ``onboard``.
        render_width: Width of ``render()`` images (px).
        render_height: Height of ``render()`` images (px).
        randomization: Per-episode domain randomization.
        rewards: Reward weights.
    """

    action_type: str = "motors"
    estimator: str = "msckf"
    frontend: str = "sim"
    imu_preset: str = "adis16448"
    scene: str = "textured_room"
    camera_width: int = 320
    camera_height: int = 240
    camera_rate_hz: float = 20.0
    ctrl_dt: float = 0.02
    inner_ctrl_dt: float = 0.005
    start: str = "air"
    obs_mode: str = "state"
    orientation: str = "rot6d"
    imu_window: int = 10
    start_p_W_m: tuple[float, float, float] = (0.0, 0.0, 1.5)
    start_position_sigma_m: float = 0.1
    start_velocity_sigma_m_s: float = 0.1
    start_tilt_sigma_rad: float = 0.05
    start_yaw_sigma_rad: float = 0.1
    init_attitude_sigma_rad: float = 0.01
    init_position_sigma_m: float = 0.02
    init_velocity_sigma_m_s: float = 0.02
    init_gyro_bias_sigma_rad_s: float = 0.002
    init_accel_bias_sigma_m_s2: float = 0.02
    ground_init_max_s: float = 10.0
    takeoff_s: float = 3.0
    arena_margin_m: float = 0.3
    max_target_distance_m: float = 3.0
    max_body_rate_rad_s: tuple[float, float, float] = (6.0, 6.0, 3.0)
    rate_bandwidth_rad_s: tuple[float, float, float] = (20.0, 20.0, 10.0)
    max_speed_m_s: float = 2.0
    max_yaw_rate_rad_s: float = 1.5
    position_range_m: float = 2.0
    render_camera: str = CHASE_CAMERA
    render_width: int = 480
    render_height: int = 360
    randomization: DomainRandomization = field(default_factory=DomainRandomization)
    rewards: RewardWeights = field(default_factory=RewardWeights)

    def __post_init__(self) -> None:
        """Reject unknown choices (listing the allowed values) and non-positive periods."""
        choices = {
            "action_type": ACTION_TYPES,
            "estimator": ESTIMATOR_NAMES,
            "frontend": FRONTEND_NAMES,
            "imu_preset": imu_preset_names(),
            "scene": tuple(SCENE_BOUNDS_M),
            "start": STARTS,
            "obs_mode": OBS_MODES,
            "orientation": ORIENTATIONS,
            "render_camera": RENDER_CAMERAS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{type(self).__name__}.{name}: unknown value {getattr(self, name)!r}; "
                    f"allowed: {', '.join(map(repr, allowed))}"
                )
        for name in ("ctrl_dt", "inner_ctrl_dt", "camera_rate_hz", "takeoff_s", "ground_init_max_s"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0.0):
                raise ValueError(f"{type(self).__name__}.{name} must be positive and finite, got {value!r}")
        if not (isinstance(self.imu_window, int) and self.imu_window >= 1):
            raise ValueError(
                f"{type(self).__name__}.imu_window must be an integer >= 1, got {self.imu_window!r}"
            )
        if not isinstance(self.randomization, DomainRandomization):
            raise ValueError(f"{type(self).__name__}.randomization must be a DomainRandomization")
        if not isinstance(self.rewards, RewardWeights):
            raise ValueError(f"{type(self).__name__}.rewards must be a RewardWeights")


@dataclass(frozen=True)
class HoverEnvConfig(VioEnvConfig):
    """Hover: hold ``start_p_W_m`` against wind gusts (0 to 1.5 N sigma, 0 to 0.5 N mean by default)."""

    randomization: DomainRandomization = field(
        default_factory=lambda: DomainRandomization(wind_mean_N=(0.0, 0.5), wind_gust_sigma_N=(0.0, 1.5))
    )


@dataclass(frozen=True)
class WaypointsEnvConfig(VioEnvConfig):
    """Waypoints: fly through ``n_waypoints`` points drawn uniformly in a box.

    Attributes:
        n_waypoints: Number of points per episode.
        waypoint_low_W_m: Lower corner of the box the points are drawn from (m).
        waypoint_high_W_m: Upper corner (m).
        reach_radius_m: A point counts as reached within this distance (m, true position).
    """

    n_waypoints: int = 4
    waypoint_low_W_m: tuple[float, float, float] = (-2.0, -2.0, 1.0)
    waypoint_high_W_m: tuple[float, float, float] = (2.0, 2.0, 2.0)
    reach_radius_m: float = 0.3
    max_target_distance_m: float = 8.0


@dataclass(frozen=True)
class TrackEnvConfig(VioEnvConfig):
    """Track: follow a figure-8 (lemniscate of Gerono) centred below/at ``start_p_W_m``.

    Attributes:
        figure8_size_m: Half-widths (a, b) along x and y (m).
        figure8_period_s: One lap at full rate (s).
        figure8_ramp_s: Smooth start of the reference's rate (s).
    """

    figure8_size_m: tuple[float, float] = (1.5, 0.75)
    figure8_period_s: float = 12.0
    figure8_ramp_s: float = 2.0


def make_config(
    config_type: type[VioEnvConfig], config: VioEnvConfig | None, overrides: dict
) -> VioEnvConfig:
    """``config`` (or the defaults of ``config_type``) with keyword overrides applied.

    Raises:
        ValueError: An unknown keyword (the message lists the allowed ones), or a bad value.
    """
    base = config if config is not None else config_type()
    if not isinstance(base, config_type):
        raise ValueError(f"config must be a {config_type.__name__}, got {type(base).__name__}")
    allowed = [f.name for f in dataclasses.fields(config_type)]
    unknown = sorted(set(overrides) - set(allowed))
    if unknown:
        raise ValueError(
            f"unknown {config_type.__name__} argument(s) {unknown}; allowed: {', '.join(allowed)}"
        )
    return dataclasses.replace(base, **overrides)


# ---------------------------------------------------------------------------------------------- rewards


def reward_tracking(position_error_m: float, weight: float, scale_m: float) -> float:
    """``weight * exp(-|e_p| / scale_m)``: in ``(0, weight]``, largest on the target."""
    return float(weight * np.exp(-position_error_m / scale_m))


def cost_effort(action: np.ndarray, neutral_action: np.ndarray, weight: float) -> float:
    """``-weight * |a - a_hover|^2``: action away from the one that holds a hover."""
    return float(-weight * np.sum((action - neutral_action) ** 2))


def cost_smoothness(action: np.ndarray, previous_action: np.ndarray, weight: float) -> float:
    """``-weight * |a_k - a_{k-1}|^2``: action changes between policy steps."""
    return float(-weight * np.sum((action - previous_action) ** 2))


def cost_crash(failed: bool, weight: float) -> float:
    """``-weight`` when the episode failed (crash, arena, divergence), else 0."""
    return -float(weight) if failed else 0.0


def reward_waypoints(n_reached: int, weight: float) -> float:
    """``weight`` per waypoint reached during this step."""
    return float(weight * n_reached)


# ---------------------------------------------------------------------------------------------- helpers


def orientation_features(R_WB: np.ndarray, kind: str) -> np.ndarray:
    """Orientation as network input: ``rot6d`` = ``[R[:, 0], R[:, 1]]`` (6,) or ``quat_wxyz``, w >= 0 (4,).

    Zhou et al., "On the continuity of rotation representations in neural networks", CVPR 2019 (6D).
    """
    if kind == "rot6d":
        return np.concatenate([R_WB[:, 0], R_WB[:, 1]])
    q = rotmat_to_quat_wxyz(R_WB)
    return -q if q[0] < 0.0 else q


def _whole_multiple(value: float, unit: float, what: str) -> int:
    """``round(value / unit)``, or a ValueError when ``value`` is not a whole multiple of ``unit``."""
    n = round(value / unit)
    if n < 1 or abs(n * unit - value) > 1e-9:
        raise ValueError(f"{what} = {value} s must be a whole multiple of {unit} s")
    return n


def _uniform(rng: np.random.Generator, lo_hi: tuple[float, float]) -> float:
    """One uniform draw in ``[low, high]`` (exactly ``low`` without a draw when the range is empty)."""
    lo, hi = lo_hi
    return float(lo) if hi == lo else float(rng.uniform(lo, hi))


class VioQuadEnv(gymnasium.Env):
    """Base class of the VIO-in-the-loop quadrotor tasks; subclasses define the targets (see module doc).

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
        self._arena_lo = np.asarray(lo) + cfg.arena_margin_m
        self._arena_hi = np.asarray(hi) - cfg.arena_margin_m
        self.action_space = spaces.Box(-1.0, 1.0, shape=(4,), dtype=np.float32)
        self.observation_space = self._observation_space()
        self._loop: ClosedLoopSim | None = None
        self._controller: SE3Controller | None = None
        self._renderer = None
        self._imu: deque = deque(maxlen=cfg.imu_window)
        self._setpoint_cache: tuple[tuple, FlatOutput] | None = None

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
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action must be finite, got {a.tolist()}")
        return np.clip(a, -1.0, 1.0)

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
        return self._controller.update(self._loop.t_s, NavState.from_estimate(est), setpoint).thrusts_N

    def _position_setpoint(self, a: np.ndarray) -> FlatOutput:
        """Setpoint of the ``position`` action: constant over a policy step, so built once per step.

        Cached on the action and the target (both fixed during a step); the validated record is reused by
        the step's ``ctrl_dt / inner_ctrl_dt`` low-level ticks instead of being rebuilt at each.
        """
        key = (a.tobytes(), self._target_est.tobytes(), self._yaw0)
        if self._setpoint_cache is None or self._setpoint_cache[0] != key:
            cfg = self.config
            setpoint = FlatOutput(
                p_W=self._target_est + a[:3] * cfg.position_range_m, yaw_rad=self._yaw0 + a[3] * np.pi
            )
            self._setpoint_cache = (key, setpoint)
        return self._setpoint_cache[1]

    # ------------------------------------------------------------------ reset

    def _rig(self, rng: np.random.Generator) -> RigConfig:
        """The episode's rig, with the wind drawn from the randomization ranges."""
        cfg, dr = self.config, self.config.randomization
        wind_mag = _uniform(rng, dr.wind_mean_N)
        wind_dir = rng.uniform(0.0, 2.0 * np.pi) if wind_mag > 0.0 else 0.0
        wind = WindParams(
            mean_force_W_N=(wind_mag * np.cos(wind_dir), wind_mag * np.sin(wind_dir), 0.0),
            gust_sigma_N=_uniform(rng, dr.wind_gust_sigma_N),
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

    def _randomize_sensor_and_body(self, loop: ClosedLoopSim, rng: np.random.Generator) -> None:
        """Scale the true IMU's noise/bias and the body's mass/inertia (estimator: nominal)."""
        dr = self.config.randomization
        noise_scale, bias_scale = _uniform(rng, dr.imu_noise_scale), _uniform(rng, dr.imu_bias_scale)
        if noise_scale != 1.0 or bias_scale != 1.0:
            p = imu_preset(self.config.imu_preset)
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
        mass_scale = _uniform(rng, dr.mass_scale)
        if mass_scale != 1.0:
            model = loop.sim.model
            body = model.body(QUAD_BODY).id
            model.body_mass[body] *= mass_scale
            model.body_inertia[body] *= mass_scale
            mujoco.mj_setConst(model, loop.sim.data)

    def _place_airborne(self, loop: ClosedLoopSim, rng: np.random.Generator) -> None:
        """Put the body at a perturbed start pose and initialize the estimator from perturbed truth."""
        cfg = self.config
        tilt = np.array([*rng.normal(0.0, cfg.start_tilt_sigma_rad, 2), 0.0])
        R_WB = rotz(rng.normal(0.0, cfg.start_yaw_sigma_rad)) @ exp_so3(tilt)
        p_WB = np.asarray(cfg.start_p_W_m, dtype=float) + rng.normal(0.0, cfg.start_position_sigma_m, 3)
        v_WB = rng.normal(0.0, cfg.start_velocity_sigma_m_s, 3)
        loop.sim.set_pose(R_WB, p_WB, v_WB)
        tr = loop.truth()
        if cfg.estimator == "ground-truth":
            loop.estimator.feed_truth(  # type: ignore[attr-defined]
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
        loop.estimator.initialize(  # type: ignore[attr-defined]
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

    def _ground_start(self, loop: ClosedLoopSim) -> None:
        """Wait on the ground for the estimator, then take off to the start point on the estimate.

        The start point is mapped into the estimator's frame through the known launch pad (``start_p_W_m``
        projected on the floor, yaw 0), not through the truth.
        """
        cfg = self.config
        while loop.estimate() is None:
            if loop.t_s >= cfg.ground_init_max_s or loop.health().diverged:
                raise RuntimeError(
                    f"estimator {cfg.estimator!r} did not initialize on the ground within "
                    f"{cfg.ground_init_max_s} s (health: {loop.health()})"
                )
            loop.advance(np.zeros(4), cfg.ctrl_dt)
        est = loop.estimate()
        pad_W = np.array(loop.config.start_p_W_m, dtype=float)
        self._R_EW = rotz(yaw_from_rotmat(est.R_WB) - loop.config.start_yaw_rad)
        self._t_EW = est.p_WB - self._R_EW @ pad_W
        start_est = self._R_EW @ np.asarray(cfg.start_p_W_m, dtype=float) + self._t_EW
        plan = Takeoff(
            est.p_WB, float(start_est[2]), duration_s=cfg.takeoff_s, yaw_rad=yaw_from_rotmat(est.R_WB)
        )
        controller = SE3Controller(self._vehicle, SE3Gains())
        t0 = loop.t_s
        while loop.t_s - t0 < cfg.takeoff_s + 1.0:
            est = loop.estimate()
            if loop.health().diverged:
                break
            cmd = controller.update(loop.t_s, NavState.from_estimate(est), plan.sample(loop.t_s - t0))
            loop.advance(cmd.thrusts_N, cfg.inner_ctrl_dt)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode (see the class docstring's Starting State); seeding only through ``seed``."""
        super().reset(seed=seed)
        rng = self.np_random
        cfg = self.config
        self.close_loop()
        rig_seed = int(rng.integers(0, 2**31 - 1))
        loop = ClosedLoopSim(self._rig(rng), seed=rig_seed)
        self._loop = loop
        self._randomize_sensor_and_body(loop, rng)
        self._R_EW, self._t_EW = np.eye(3), np.zeros(3)
        if cfg.start == "air":
            self._place_airborne(loop, rng)
        else:
            self._ground_start(loop)
        self._task_reset(rng)
        self._controller = SE3Controller(self._vehicle, SE3Gains())
        est = loop.estimate()
        self._yaw0 = yaw_from_rotmat(est.R_WB) if est is not None else 0.0
        self._yaw_setpoint = self._yaw0
        self._t_task = 0.0
        self._prev_action = self._neutral.copy()
        self._imu.clear()
        self._collect_imu()
        self._update_target()
        return self._get_obs(), self._get_info({}, "")

    # ------------------------------------------------------------------ step

    def _collect_imu(self) -> None:
        imu = self._loop.last_imu
        if imu is not None and (not self._imu or self._imu[-1].t_s != imu.t_s):
            self._imu.append(imu)

    def _update_target(self) -> None:
        """Target now, in the world (reward) and estimator (observation) frames."""
        p, v = self._target_W(self._t_task)
        self._target_true_W, self._target_v_W = p, v
        self._target_est = self._R_EW @ p + self._t_EW
        self._target_v_est = self._R_EW @ v

    def step(self, action):
        """Hold ``action`` for ``ctrl_dt``; returns ``(obs, reward, terminated, truncated, info)``."""
        if self._loop is None:
            raise RuntimeError("call reset() before step()")
        a = self._check_action(action)
        loop = self._loop
        reason = ""
        for _ in range(self._n_inner):
            est = loop.estimate()
            if est is None or loop.health().diverged or not np.all(np.isfinite(est.p_WB)):
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
        if not reason and (np.any(tr.p_WB < self._arena_lo) or np.any(tr.p_WB > self._arena_hi)):
            reason = "left_arena"
        err = float(np.linalg.norm(tr.p_WB - self._target_true_W))
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
        return self._get_obs(), reward, bool(reason), False, self._get_info(components, reason)

    # ------------------------------------------------------------------ observation and info

    def _state_vector(self) -> np.ndarray:
        est = self._loop.estimate()
        health = self._loop.health()
        if est is None:
            parts = [np.zeros(n) for _, n, _, _ in self._state_layout()]
        else:
            parts = [
                est.p_WB - self._target_est,
                est.v_WB,
                orientation_features(est.R_WB, self.config.orientation),
                est.omega_B_rad_s,
                self._target_est,
                self._target_v_est,
                np.diag(est.cov)[3:6],
                np.diag(est.cov)[6:9],
                [float(health.tracked_features)],
            ]
        vec = np.nan_to_num(np.concatenate(parts).astype(np.float32), nan=0.0, posinf=1e6, neginf=-1e6)
        space = self.observation_space if self.config.obs_mode == "state" else self.observation_space["state"]
        return np.clip(vec, space.low, space.high)

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
        """Ground truth and diagnostics (never part of the observation)."""
        tr = self._loop.truth()
        est = self._loop.estimate()
        health = self._loop.health()
        info = {
            "t_s": tr.t_s,
            "p_true_W_m": tr.p_WB.copy(),
            "v_true_W_m_s": tr.v_WB.copy(),
            "R_true_WB": tr.R_WB.copy(),
            "target_W_m": self._target_true_W.copy(),
            "position_error_m": float(np.linalg.norm(tr.p_WB - self._target_true_W)),
            "estimate_error_m": np.nan,
            "tracked_features": int(health.tracked_features),
            "conditions": tuple(health.conditions),
            "termination_reason": reason,
            "reward_components": dict(components),
        }
        if est is not None:
            p_est_W = self._R_EW.T @ (est.p_WB - self._t_EW)
            info["estimate_error_m"] = float(np.linalg.norm(p_est_W - tr.p_WB))
        for name, value in components.items():
            info[f"reward_{name}"] = value
        return info

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


# ---------------------------------------------------------------------------------------------- tasks

_DOC_COMMON = """
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
    ``R_true_WB``, ``position_error_m``, ``estimate_error_m``).

    ## Rewards
    Sum of ``info["reward_components"]`` (also ``info["reward_<name>"]``), computed from the TRUE position:
    ``tracking = w * exp(-|p - p_target| / tracking_scale_m)``, ``effort = -w |a - a_hover|^2``,
    ``smoothness = -w |a_k - a_(k-1)|^2``, ``crash = -w`` on a failed episode{extra_rewards}.

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

    ## Episode End
    Terminated on a crash (contact, tilt over 80 deg), leaving the arena (the scene's free space shrunk by
    ``arena_margin_m``), being farther than ``max_target_distance_m`` from the target, or estimator
    divergence (``health.diverged``){extra_end}; ``info["termination_reason"]`` says which. Truncation:
    only by the ``TimeLimit`` of the registration (``max_episode_steps``; override it in ``gymnasium.make``).

    ## Arguments
    ``render_mode`` (``None`` or ``"rgb_array"``: the ``chase`` camera, or ``render_camera="onboard"``;
    ``env.unwrapped.render_camera(name)`` renders either), ``config`` (a ``{config}``), and any field of
    ``{config}`` as a keyword (``action_type``, ``estimator``, ``frontend``, ``imu_preset``, ``camera_width``,
    ``camera_height``, ``ctrl_dt``, ``randomization``, ``obs_mode``, ...). Unknown names or values raise
    ``ValueError`` listing the allowed ones.

    ## Version History
    - v0: initial version.
"""


class HoverEnv(VioQuadEnv):
    """Hold a point against wind gusts, flying on the VIO estimate (``viotb/Hover-v0``).

    ## Description
    A 1.2 kg quadrotor in the textured room must hold ``start_p_W_m`` (1.5 m above the origin) while
    horizontal wind gusts push it; its observations come from the estimator (MSCKF on simulated features by
    default), so estimator drift shows up as hover error that the policy cannot see.
    """

    config_type = HoverEnvConfig

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return np.asarray(self.config.start_p_W_m, dtype=float), np.zeros(3)


class WaypointsEnv(VioQuadEnv):
    """Fly through a random sequence of points on the VIO estimate (``viotb/Waypoints-v0``).

    ## Description
    ``n_waypoints`` points are drawn uniformly in a box at reset; the target is the current point, and it
    advances when the TRUE position comes within ``reach_radius_m`` (the simulator is the referee). The
    observation's target switches then.
    """

    config_type = WaypointsEnvConfig

    def _task_reset(self, rng: np.random.Generator) -> None:
        cfg = self.config
        lo, hi = np.asarray(cfg.waypoint_low_W_m), np.asarray(cfg.waypoint_high_W_m)
        self.waypoints_W = rng.uniform(lo, hi, size=(cfg.n_waypoints, 3))
        self._index = 0

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        return self.waypoints_W[min(self._index, len(self.waypoints_W) - 1)].copy(), np.zeros(3)

    def _task_step(self, p_true_W: np.ndarray) -> tuple[dict[str, float], bool]:
        n = len(self.waypoints_W)
        reached = 0
        if (
            self._index < n
            and np.linalg.norm(p_true_W - self.waypoints_W[self._index]) < self.config.reach_radius_m
        ):
            reached = 1
            self._index += 1
        return {"waypoint": reward_waypoints(reached, self.config.rewards.waypoint)}, self._index >= n


class TrackEnv(VioQuadEnv):
    """Follow a moving figure-8 reference on the VIO estimate (``viotb/Track-v0``).

    ## Description
    The target moves along a lemniscate of Gerono (``controllers.setpoints.FigureEight``) centred at
    ``start_p_W_m``, starting at rest there; the observation includes its position and velocity.
    """

    config_type = TrackEnvConfig

    def _task_reset(self, rng: np.random.Generator) -> None:
        cfg = self.config
        c = np.asarray(cfg.start_p_W_m, dtype=float)
        self._figure8 = FigureEight(
            center_xy_m=c[:2],
            size_m=np.asarray(cfg.figure8_size_m, dtype=float),
            period_s=cfg.figure8_period_s,
            altitude_m=float(c[2]),
            ramp_s=cfg.figure8_ramp_s,
        )

    def _target_W(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        s = self._figure8.sample(t_s)
        return np.array(s.p_W), np.array(s.v_W)


for _env_class, _extra_rewards, _extra_end in (
    (HoverEnv, "", ""),
    (
        WaypointsEnv,
        ", and ``waypoint = w`` per point reached",
        ", or success after the last point (no penalty)",
    ),
    (TrackEnv, "", ""),
):
    _env_class.__doc__ += _DOC_COMMON.format(
        extra_rewards=_extra_rewards, extra_end=_extra_end, config=_env_class.config_type.__name__
    )
