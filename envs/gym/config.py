"""Configuration of the Gymnasium tasks: one frozen dataclass per env, every tunable once, validated."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np
from viotb.envs.sim.imu_model import imu_preset_names
from viotb.models.constants import CHASE_CAMERA, ONBOARD_CAMERA, SCENE_BOUNDS_M
from viotb.vio.factory import ESTIMATOR_NAMES, FRONTEND_NAMES

ACTION_TYPES = ("motors", "ctbr", "velocity", "position")
"""``motors``: normalized thrusts; ``ctbr``: collective thrust + body rates; ``velocity`` / ``position``:
setpoints through the SE(3) controller."""
INFO_MODES = ("full", "flat")
"""``info`` per step: ``full`` (truth arrays, conditions, nested reward terms) or ``flat`` (scalars only)."""
OBS_MODES = ("state", "dict")
"""``state``: one flat Box; ``dict``: ``{"state", "image", "imu"}``."""
ORIENTATIONS = ("rot6d", "quat")
STARTS = ("air", "ground")
RENDER_CAMERAS = (CHASE_CAMERA, ONBOARD_CAMERA)
FAILURE_REASONS = ("crashed", "left_arena", "too_far", "diverged")
"""Termination reasons that cost the crash penalty (``success`` does not)."""


# ---------------------------------------------------------------------------------------------- checks


def _is_number(value: object) -> bool:
    return isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool | np.bool_
    )


def _check_number(cfg: object, name: str, low: float, strict: bool) -> None:
    """``cfg.name`` is a finite number ``> low`` (``strict``) or ``>= low``; else a ValueError naming it."""
    value = getattr(cfg, name)
    rule = f"{'>' if strict else '>='} {low:g}"
    ok = _is_number(value) and np.isfinite(value) and (value > low if strict else value >= low)
    if not ok:
        raise ValueError(f"{type(cfg).__name__}.{name} must be a finite number {rule}, got {value!r}")


def _check_vector(cfg: object, name: str, size: int, low: float | None = None) -> None:
    """``cfg.name`` is ``size`` finite numbers (each ``> low`` when given); else a ValueError naming it."""
    value = getattr(cfg, name)
    ok = isinstance(value, tuple | list | np.ndarray) and len(value) == size and all(map(_is_number, value))
    ok = ok and bool(np.all(np.isfinite(np.asarray(value, dtype=float))))
    ok = ok and (low is None or bool(np.all(np.asarray(value, dtype=float) > low)))
    if not ok:
        rule = f"{size} finite numbers" + ("" if low is None else f" > {low:g}")
        raise ValueError(f"{type(cfg).__name__}.{name} must be {rule}, got {value!r}")


def _check_int(cfg: object, name: str, low: int) -> None:
    """``cfg.name`` is an integer ``>= low``; else a ValueError naming it."""
    value = getattr(cfg, name)
    if not (isinstance(value, int | np.integer) and not isinstance(value, bool) and value >= low):
        raise ValueError(f"{type(cfg).__name__}.{name} must be an integer >= {low}, got {value!r}")


_POSITIVE = (
    "ctrl_dt",
    "inner_ctrl_dt",
    "camera_rate_hz",
    "takeoff_s",
    "ground_init_max_s",
    "max_target_distance_m",
    "max_speed_m_s",
    "max_yaw_rate_rad_s",
)
_NON_NEGATIVE = (
    "start_position_sigma_m",
    "start_velocity_sigma_m_s",
    "start_tilt_sigma_rad",
    "start_yaw_sigma_rad",
    "init_attitude_sigma_rad",
    "init_position_sigma_m",
    "init_velocity_sigma_m_s",
    "init_gyro_bias_sigma_rad_s",
    "init_accel_bias_sigma_m_s2",
    "arena_margin_m",
    "position_range_m",
)
_PIXELS = ("camera_width", "camera_height", "render_width", "render_height")


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
        info: ``full`` (truth arrays, conditions, nested reward terms) or ``flat`` (the scalars only, for
            vector envs): ``viotb.envs.gym.info.INFO_MODES``.
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
    info: str = "full"
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
            "info": INFO_MODES,
            "orientation": ORIENTATIONS,
            "render_camera": RENDER_CAMERAS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(
                    f"{type(self).__name__}.{name}: unknown value {getattr(self, name)!r}; "
                    f"allowed: {', '.join(map(repr, allowed))}"
                )
        for name in _POSITIVE:
            _check_number(self, name, 0.0, strict=True)
        for name in _NON_NEGATIVE:
            _check_number(self, name, 0.0, strict=False)
        for name in (*_PIXELS, "imu_window"):
            _check_int(self, name, 1)
        _check_vector(self, "start_p_W_m", 3)
        _check_vector(self, "max_body_rate_rad_s", 3, low=0.0)
        _check_vector(self, "rate_bandwidth_rad_s", 3, low=0.0)
        lo, hi = (np.asarray(b, dtype=float) for b in SCENE_BOUNDS_M[self.scene])
        half = float(np.min(hi - lo)) / 2.0
        if not self.arena_margin_m < half:
            raise ValueError(
                f"{type(self).__name__}.arena_margin_m must be < {half:g} m (half the smallest extent of the "
                f"{self.scene!r} scene), got {self.arena_margin_m!r}"
            )
        p = np.asarray(self.start_p_W_m, dtype=float)
        a_lo, a_hi = lo + self.arena_margin_m, hi - self.arena_margin_m
        if np.any(p < a_lo) or np.any(p > a_hi):
            raise ValueError(
                f"{type(self).__name__}.start_p_W_m {self.start_p_W_m!r} is outside the arena of the "
                f"{self.scene!r} scene ({a_lo.tolist()} to {a_hi.tolist()} m)"
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

    def __post_init__(self) -> None:
        """The shared checks, then the waypoint box and radius."""
        super().__post_init__()
        _check_int(self, "n_waypoints", 1)
        _check_vector(self, "waypoint_low_W_m", 3)
        _check_vector(self, "waypoint_high_W_m", 3)
        if np.any(np.asarray(self.waypoint_low_W_m) > np.asarray(self.waypoint_high_W_m)):
            raise ValueError(
                f"WaypointsEnvConfig.waypoint_low_W_m {self.waypoint_low_W_m!r} must be <= waypoint_high_W_m "
                f"{self.waypoint_high_W_m!r}"
            )
        _check_number(self, "reach_radius_m", 0.0, strict=True)


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

    def __post_init__(self) -> None:
        """The shared checks, then the figure-8's size, period and ramp."""
        super().__post_init__()
        _check_vector(self, "figure8_size_m", 2, low=0.0)
        _check_number(self, "figure8_period_s", 0.0, strict=True)
        _check_number(self, "figure8_ramp_s", 0.0, strict=False)


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
