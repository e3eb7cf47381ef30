"""The options of ``viotb eval`` (:class:`EvalOptions`), and why a metric can be null (``NULL_REASONS``)."""

from __future__ import annotations

from dataclasses import dataclass
from types import MappingProxyType

from viotb.envs.data.validate import IMU_GAP_POLICIES
from viotb.envs.run.loop_glue import LoopOptions
from viotb.vio.health import HealthParams
from viotb.vio.msckf_params import MsckfParams
from viotb.vio.window import WindowParams

NULL_REASONS = MappingProxyType(
    {
        "rpe_1m_pct": "no two evaluated poses 1 m apart along the ground-truth path",
        "scale_error_pct": "the evaluated path is too short to measure a scale",
        "drift_pct": "the evaluated path is too short to measure drift",
        "ms_per_frame_median": "no frame was processed",
        "ms_per_frame_p99": "no frame was processed",
    }
)
"""Why a metric of :func:`evaluate_dataset` can be NaN (``--json`` prints ``null`` with this reason)."""


@dataclass(frozen=True)
class EvalOptions:
    """Options of one evaluation run.

    Attributes:
        estimator: Estimator name (see ``viotb.vio.factory.ESTIMATOR_NAMES``).
        frontend: ``"klt"`` (OpenCV on the images, default) or ``"sim"`` (projections of the dataset's
            ``sim_landmarks0`` with ground-truth poses plus pixel noise; recorded datasets only).
        seed: Seed of the pixel noise in the ``sim`` front end.
        sim_pixel_sigma_px: Pixel noise (px) of the ``sim`` front end.
        max_frames: Stop after this many frames (None = all; >= 0).
        msckf: MSCKF settings (None: the defaults).
        window: Window-optimizer settings (None: the defaults).
        imu_gap_policy: What to do with a gap in ``imu0/data.csv`` longer than ``imu_gap_tolerance_periods``
            nominal periods: ``refuse`` (a ValueError naming file, lines and times) or ``bridge`` (linear
            interpolation at the nominal rate, reported in ``imu_gaps`` and ``notes``).
        imu_gap_tolerance_periods: Longest normal spacing of IMU samples, in nominal periods (> 1).
        cameras: 1 (``cam0`` only, the default, so results on stereo folders match earlier runs) or 2
            (``cam0`` and ``cam1``: ``calib_right`` to the estimator, ``image_right`` / ``features_right``
            in each frame).
        monitor: Run the health monitor beside the estimator (result ``conditions``).
        calibrate: Estimate the camera-IMU time offset and extrinsics online (``msckf``:
            ``MsckfParams.with_online_calibration``; ``window``: ``WindowParams.with_online_calibration``;
            result ``calibration``). The conditions are those of the first pass, which starts from the file's
            calibration; each further pass starts from the previous pass's estimate (an EKF does not undo
            the linearization errors of a large initial offset: 10 ms in the file left 1.2-1.4 ms after one
            10 s pass, 0.06-0.25 ms after two), and the metrics are those of the last pass.
        calibration_passes: Passes with ``calibrate`` (1 or more).
        health: Monitor thresholds (None: the defaults, with the NIS reference of
            :func:`viotb.envs.data.diagnosis.expected_nis_per_dof`).
        report: Write the report (PNGs, ``report.json``) into the output folder
            (:mod:`viotb.envs.tools.eval_report`).
        rerun: With ``report``, also write a rerun recording ``eval.rrd``.
        loop: Loop closure beside the estimator (:class:`~viotb.envs.run.loop_glue.LoopOptions`); None = off.
    """

    estimator: str = "msckf"
    frontend: str = "klt"
    seed: int = 0
    sim_pixel_sigma_px: float = 0.5
    max_frames: int | None = None
    msckf: MsckfParams | None = None
    window: WindowParams | None = None
    cameras: int = 1
    imu_gap_policy: str = "refuse"
    imu_gap_tolerance_periods: float = 5.0
    monitor: bool = True
    calibrate: bool = False
    calibration_passes: int = 2
    health: HealthParams | None = None
    report: bool = False
    rerun: bool = False
    loop: LoopOptions | None = None

    def __post_init__(self) -> None:
        """Reject a negative ``max_frames``, an unknown gap policy and a tolerance <= 1 period."""
        if self.max_frames is not None and not (isinstance(self.max_frames, int) and self.max_frames >= 0):
            raise ValueError(f"max_frames must be an integer >= 0, got {self.max_frames!r}")
        if self.imu_gap_policy not in IMU_GAP_POLICIES:
            raise ValueError(
                f"unknown IMU gap policy {self.imu_gap_policy!r}; allowed: {', '.join(IMU_GAP_POLICIES)}"
            )
        if not self.imu_gap_tolerance_periods > 1.0:
            raise ValueError(f"imu_gap_tolerance_periods must be > 1, got {self.imu_gap_tolerance_periods!r}")
        if self.cameras not in (1, 2):
            raise ValueError(f"cameras must be 1 or 2, got {self.cameras!r}")
        if not (isinstance(self.calibration_passes, int) and self.calibration_passes >= 1):
            raise ValueError(f"calibration_passes must be an integer >= 1, got {self.calibration_passes!r}")
