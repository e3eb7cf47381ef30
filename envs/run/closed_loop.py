"""Lockstep closed-loop core: physics, IMU, camera and estimator advanced together in timestamp order.

One :class:`ClosedLoopSim` owns a :class:`~viotb.envs.sim.simulation.Simulation`, the IMU and camera sensor
models, an offscreen renderer (image front end) or the landmark projector (``sim`` fast mode), and an
estimator chosen by name. Callers (the ``viotb fly`` runner and the Gymnasium envs) hold motor thrusts for one
control period with :meth:`ClosedLoopSim.advance`; inside it:

1. physics steps at the model's timestep (``<option timestep>``);
2. every IMU period the noiseless gyro/accelerometer of the ``imu`` site go through the IMU model and the
   sample is fed to the estimator (and logged);
3. at each camera exposure time (IMU clock) the camera is rendered and its frame, stamped on the camera clock
   (``t_cam = t_imu - time_offset_s``), is queued; it reaches the estimator ``latency_s`` later, after every
   IMU sample up to its arrival time;
4. external wind force is applied to the body.

Nothing of the truth reaches the estimator: only IMU samples and camera frames (the ``ground-truth`` estimator
is the explicit exception, fed truth for fast policy training).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass, replace
from functools import partial

import mujoco
import numpy as np
from viotb.envs.sim.imu_model import ImuModel, imu_preset
from viotb.envs.sim.render import OffscreenRenderer, SceneLights, camera_calibration
from viotb.envs.sim.rig import RigConfig
from viotb.envs.sim.simulation import Simulation
from viotb.models.constants import ONBOARD_CAMERA, QUAD_BODY, SCENE_BOUNDS_M
from viotb.vio.factory import CALIBRATING_ESTIMATORS, make_estimator
from viotb.vio.msckf import MsckfParams
from viotb.vio.recovery import RECOVERABLE_ESTIMATORS, RecoveringEstimator, cold_start_msckf_params
from viotb.vio.types import CameraFrame, FeatureObservations, HealthStatus, ImuSample, StateEstimate
from viotb.vio.window import WindowParams


@dataclass(frozen=True)
class TruthState:
    """Ground truth of the body (for logging, metrics and ``info`` only).

    Attributes:
        t_s: Time (s).
        R_WB: shape (3, 3).
        p_WB: (m), shape (3,).
        v_WB: (m/s), shape (3,).
        omega_B: (rad/s), shape (3,).
    """

    t_s: float
    R_WB: np.ndarray
    p_WB: np.ndarray
    v_WB: np.ndarray
    omega_B: np.ndarray


_COS_MAX_TILT = math.cos(math.radians(80.0))
"""Crash test: a body z axis more than 80 deg from vertical."""


def _read_only(arr: np.ndarray) -> np.ndarray:
    arr.setflags(write=False)
    return arr


_ZERO3 = _read_only(np.zeros(3))
_ZERO_COV = _read_only(np.zeros((15, 15)))
"""The truth's biases and covariance (zero), shared read-only by every ``ground-truth`` feed."""


def _rotz(yaw: float) -> np.ndarray:
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class ClosedLoopSim:
    """The lockstep rig (see the module docstring).

    Args:
        config: The rig.
        seed: Seeds every random component (IMU noise and biases, pixel noise, drops, wind).

    Raises:
        ValueError: Unknown scene, estimator, front end or preset; IMU/camera periods that are not whole
            multiples of the physics timestep.
    """

    def __init__(self, config: RigConfig, seed: int = 0) -> None:
        """Build the simulation, sensors, renderer and estimator."""
        if config.frontend not in ("klt", "sim"):
            raise ValueError(f"unknown front end {config.frontend!r}; allowed: 'klt', 'sim'")
        self.config = config
        self.sim = Simulation("quadrotor", config.scene)
        rng = np.random.default_rng(seed)
        self._rng_imu, self._rng_pix, self._rng_cam, self._rng_wind, self._rng_lm = rng.spawn(5)
        dt = self._dt = self.sim.timestep_s
        imu_params = imu_preset(config.imu_preset)
        self.imu_model = ImuModel(imu_params, self._rng_imu)
        self._imu_every = self._steps_per_period(1.0 / imu_params.rate_hz, "IMU", dt)
        self._cam_every = self._steps_per_period(1.0 / config.camera.rate_hz, "camera", dt)
        cam = config.camera
        self.calib = camera_calibration(
            self.sim.model, ONBOARD_CAMERA, QUAD_BODY, cam.width, cam.height, cam.time_offset_s, cam.rate_hz
        )
        given = config.faults.told_calibration(self.calib)
        self.calib_given = given  # what the estimator is told; self.calib is the truth
        # The fast mode knows its own pixel noise (as the open-loop streams do): a filter told 1 px while the
        # simulated features carry 0.5 px has a nominal NIS per dof of 0.25, and the monitor's time-sync test
        # (NIS > 1.25 while moving) never fires.
        params = config.msckf if config.msckf is not None else MsckfParams()
        window_params = config.window if config.window is not None else WindowParams()
        if config.frontend == "sim":
            params = replace(params, pixel_sigma_px=config.sim_pixel_sigma_px)
            window_params = replace(window_params, pixel_sigma_px=config.sim_pixel_sigma_px)
        if config.online_calibration:
            if config.estimator not in CALIBRATING_ESTIMATORS:
                raise ValueError(
                    f"online calibration needs the msckf or window estimator, got {config.estimator!r}"
                )
            params = params.with_online_calibration()
            window_params = window_params.with_online_calibration()
        make = partial(
            make_estimator,
            config.estimator,
            given,
            imu_params.noise,
            frontend=config.frontend,
            params=params,
            window_params=window_params,
        )
        if config.recovery and config.estimator in RECOVERABLE_ESTIMATORS:
            # Coasts through a loss of tracking and re-initializes in the air (viotb.vio.recovery).
            reinit = partial(make, params=cold_start_msckf_params(params))
            self.estimator = RecoveringEstimator(make, given, imu_params.noise, make_reinit=reinit)
        else:
            self.estimator = make()
        need_images = config.frontend == "klt" or config.render_images
        self.renderer = (
            OffscreenRenderer(
                self.sim.model, cam.width, cam.height, ONBOARD_CAMERA, cam.pixel_noise_std, self._rng_pix
            )
            if need_images
            else None
        )
        self.landmarks_W = None
        if config.frontend == "sim":
            from viotb.envs.sim.landmarks import scene_landmarks

            self.landmarks_W = scene_landmarks(self.sim.model, self._rng_lm)
        self._blackouts = tuple(cam.blackout_intervals_s)
        self._lights_off = tuple(config.lights_off_intervals_s)
        self._lights = SceneLights(self.sim.model) if self._lights_off else None
        self._bounds = SCENE_BOUNDS_M.get(config.scene)
        # Crash box: the scene bounds widened by 0.5 m (built once; read every low-level tick).
        # Crash box as float triples (the per-tick test compares floats, not arrays).
        self._crash_lo = None if self._bounds is None else tuple(np.subtract(self._bounds[0], 0.5).tolist())
        self._crash_hi = None if self._bounds is None else tuple(np.add(self._bounds[1], 0.5).tolist())
        # truth() memo: the TruthState of one physics state, keyed on (time, qpos, qvel) (see truth()).
        self._truth_key: tuple | None = None
        self._truth: TruthState | None = None
        self._truth_fed: TruthState | None = None
        self._pending: deque[tuple[float, CameraFrame]] = deque()
        self._wind_gust_W = (0.0, 0.0, 0.0)  # gust force (N) in W, plain floats
        # The gust's normals, 256 triples drawn at once: the same draws in the same order as one
        # standard_normal(3) per update (numpy's Generator keeps no state between calls).
        self._wind_normals: list[list[float]] = []
        self._wind_next = 0
        self._gust_decay: dict[tuple[float, float], tuple[float, float]] = {}
        self._step_count = 0
        self.last_frame: CameraFrame | None = None
        self.last_imu: ImuSample | None = None
        self.simulate_imu = True
        """False skips the IMU model (its own random stream) at every sample time: for a consumer that reads
        no IMU sample, e.g. a ``ground-truth`` estimator under a state-only observation (the Gymnasium envs);
        :attr:`last_imu` then stays as it was. The physics chunks keep their IMU-period boundaries."""
        self.frames_delivered = 0
        self.frames_dropped = 0
        self.estimator_failure = ""
        self._place_on_ground()

    @staticmethod
    def _steps_per_period(period_s: float, what: str, dt: float) -> int:
        n = round(period_s / dt)
        if n < 1 or abs(n * dt - period_s) > 1e-9:
            raise ValueError(
                f"{what} period {period_s} s is not a whole multiple of the physics timestep {dt} s"
            )
        return n

    def _place_on_ground(self) -> None:
        self.sim.reset(None)
        self.sim.set_pose(_rotz(self.config.start_yaw_rad), np.asarray(self.config.start_p_W_m, dtype=float))
        self.sim.data.ctrl[:] = 0.0
        mujoco.mj_forward(self.sim.model, self.sim.data)

    # ------------------------------------------------------------------ readers

    @property
    def t_s(self) -> float:
        """Simulation time (s) = IMU clock."""
        return self.sim.time_s

    def truth(self) -> TruthState:
        """Ground truth now (never fed to an estimator other than ``ground-truth``); read-only arrays.

        Memoized on the physics state: the readers (pose from the ``imu_quat`` sensor, velocity, gyro) are
        functions of ``(time, qpos, qvel)`` after ``mj_forward``, which both :meth:`advance` and
        ``Simulation.set_pose`` end with, so the same state returns the same record (the env reads the
        truth several times per low-level tick: the ``ground-truth`` estimate, the crash test, ``info``).
        """
        key = self.sim.state_key()
        if key != self._truth_key:
            self._truth_key, self._truth = key, TruthState(float(key[0]), *self.sim.body_state())
        return self._truth

    def estimate(self) -> StateEstimate | None:
        """The estimator's latest state (propagated to the newest IMU sample), or None before init.

        The ``ground-truth`` pass-through is fed the truth here, when asked, rather than at every IMU sample.
        """
        if self.config.estimator == "ground-truth":
            self._feed_truth()
        return self.estimator.estimate()

    def health(self) -> HealthStatus:
        """The estimator's health."""
        return self.estimator.health()

    def crashed(self, airborne: bool) -> bool:
        """Crash test: contact once airborne, tilt beyond 80 deg, or leaving the scene bounds."""
        tr = self.truth()
        if tr.R_WB[2, 2] < _COS_MAX_TILT:
            return True
        if self._crash_lo is not None:
            p0, p1, p2 = tr.p_WB.tolist()
            lo0, lo1, lo2 = self._crash_lo
            hi0, hi1, hi2 = self._crash_hi
            if p0 < lo0 or p1 < lo1 or p2 < lo2 or p0 > hi0 or p1 > hi1 or p2 > hi2:
                return True
        return airborne and self.sim.in_collision()

    # ------------------------------------------------------------------ stepping

    def _in_blackout(self, t: float) -> bool:
        return any(a <= t < b for a, b in self._blackouts)

    def _capture(self, t_exposure: float) -> None:
        """Render / project a frame at the current state, queue it for delivery after the latency."""
        cam = self.config.camera
        if self.config.estimator == "ground-truth" and not self.config.render_images:
            return  # the pass-through estimator ignores frames: skip rendering/projection (fast training)
        if self._in_blackout(t_exposure) or self._rng_cam.random() < cam.drop_probability:
            self.frames_dropped += 1
            return
        t_cam = t_exposure - cam.time_offset_s
        dark = any(a <= t_exposure < b for a, b in self._lights_off)
        if self._lights is not None:
            self._lights.set_on(not dark)
        image = self.renderer.render_gray(self.sim.data) if self.renderer is not None else None
        features = None
        if self.config.frontend == "sim" and dark:
            features = FeatureObservations(ids=np.zeros(0, dtype=np.int64), uv_px=np.zeros((0, 2)))
        elif self.config.frontend == "sim":
            from viotb.envs.sim.landmarks import project_landmarks

            R_WC, p_WC = self.sim.camera_pose()
            features = project_landmarks(
                self.landmarks_W, R_WC, p_WC, self.calib.camera, self._rng_pix, self.config.sim_pixel_sigma_px
            )
        self._pending.append(
            (t_exposure + cam.latency_s, CameraFrame(t_s=t_cam, image=image, features=features))
        )

    def _deliver_frames(self) -> None:
        while self._pending and self._pending[0][0] <= self.t_s + 1e-12:
            _, frame = self._pending.popleft()
            self._feed(self.estimator.feed_camera, frame)
            self.last_frame = frame
            self.frames_delivered += 1

    def _feed(self, feed, item) -> None:
        """Feed the estimator; an estimator that raises is recorded as failed and fed no more.

        The process must survive a broken estimator (bad samples it rejects, numerical failure): the runner
        reads :attr:`estimator_failure` and stops the flight, reporting it as a divergence.
        """
        if self.estimator_failure:
            return
        try:
            feed(item)
        except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
            self.estimator_failure = f"{type(exc).__name__}: {exc}"

    def _feed_truth(self) -> None:
        tr = self.truth()
        if tr is self._truth_fed:
            return  # this physics state was already fed (same record, same estimate)
        self._truth_fed = tr
        self.estimator.feed_truth(
            StateEstimate(
                t_s=tr.t_s,
                R_WB=tr.R_WB,
                p_WB=tr.p_WB,
                v_WB=tr.v_WB,
                gyro_bias_rad_s=_ZERO3,
                accel_bias_m_s2=_ZERO3,
                omega_B_rad_s=tr.omega_B,
                cov=_ZERO_COV,
            )
        )

    def _apply_wind(self, dt: float) -> None:
        w = self.config.wind
        if w.gust_sigma_N <= 0.0 and not any(w.mean_force_W_N):
            return  # calm air: xfrc_applied stays zero
        if w.gust_sigma_N > 0.0:
            # First-order Gauss-Markov gust: the decay and its noise scale depend on dt only (memoized).
            key = (dt, w.gust_time_constant_s)
            decay = self._gust_decay.get(key)
            if decay is None:
                a = float(np.exp(-dt / w.gust_time_constant_s))
                decay = self._gust_decay[key] = (a, float(np.sqrt(1.0 - a * a)))
            a, scale = decay
            # Per axis in plain floats: (n sigma) scale, then a g + noise, the vertical noise zero.
            if self._wind_next == len(self._wind_normals):
                self._wind_normals, self._wind_next = self._rng_wind.standard_normal((256, 3)).tolist(), 0
            n0, n1, _ = self._wind_normals[self._wind_next]
            self._wind_next += 1
            sigma = w.gust_sigma_N
            g0, g1, g2 = self._wind_gust_W
            self._wind_gust_W = (a * g0 + n0 * sigma * scale, a * g1 + n1 * sigma * scale, a * g2 + 0.0)
        m0, m1, m2 = w.mean_force_W_N
        g0, g1, g2 = self._wind_gust_W
        self.sim.set_body_force_W(m0 + g0, m1 + g1, m2 + g2)

    def advance(self, thrusts_N: np.ndarray, duration_s: float) -> None:
        """Hold motor thrusts for ``duration_s`` (rounded to physics steps), running sensors and estimator.

        Args:
            thrusts_N: Motor thrusts (N), shape (4,); MuJoCo clips them to the actuators' ctrlrange.
            duration_s: Time to advance (s), at least one physics step.
        """
        dt = self._dt
        n = max(1, round(duration_s / dt))
        imu_every, cam_every = self._imu_every, self._cam_every
        ctrl = self.sim.checked_ctrl(thrusts_N)
        done = 0
        while done < n:
            # Step the physics in one call up to the next sensor event (IMU sample, exposure, frame arrival);
            # mj_forward between plain steps would only recompute what the next mj_step computes again.
            count = self._step_count
            chunk = min(n - done, imu_every - count % imu_every, cam_every - count % cam_every)
            if self._pending:
                chunk = min(chunk, max(1, math.ceil((self._pending[0][0] - self.t_s) / dt - 1e-9)))
            self._apply_wind(dt * chunk)
            self.sim.step_checked(ctrl, chunk)
            self._step_count = count = count + chunk
            done += chunk
            if self.simulate_imu and count % imu_every == 0:
                omega_B, f_B = self.config.faults.imu_input(
                    self.sim.angular_velocity_B(), self.sim.specific_force_B()
                )
                sample = self.imu_model.measure(self.t_s, omega_B, f_B)
                fault = self.config.imu_fault_at_s
                if fault is not None and self.t_s >= fault:
                    nan3 = np.full(3, np.nan)
                    sample = ImuSample(sample.t_s, nan3, nan3, sample.saturated)
                self.last_imu = sample
                self._feed(self.estimator.feed_imu, sample)
            if count % cam_every == 0:
                self._capture(self.t_s)
            if self._pending:
                self._deliver_frames()

    def close(self) -> None:
        """Release the GL context."""
        if self.renderer is not None:
            self.renderer.close()
            self.renderer = None
