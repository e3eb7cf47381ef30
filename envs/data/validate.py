"""Range checks of what a EuRoC folder says, where it is read (:mod:`.euroc`), and the IMU gap policy.

Every message names the file, the field (or line) and the value, so that a user can fix the file. The
structural checks (missing fields, non-numbers, non-finite values, non-monotonic stamps) stay in the reader;
this module holds the physical ranges and the stream-level checks that need more than one line.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

IMU_GAP_POLICIES = ("refuse", "bridge")
"""``refuse``: an IMU gap beyond the tolerance is an error; ``bridge``: the gap is filled by linear
interpolation at the nominal rate and reported."""
MAX_TIMESHIFT_S = 1.0
"""Largest camera-IMU clock offset (s) accepted in a ``sensor.yaml`` (calibrations are milliseconds)."""


def _range_error(path: Path, field: str, value: object, rule: str) -> ValueError:
    return ValueError(f"{path}: field {field!r} {rule}, got {value!r}")


def check_camera_ranges(
    path: Path,
    intrinsics: tuple[float, float, float, float],
    resolution: tuple[int, int],
    rate_hz: float,
    timeshift_s: float,
) -> None:
    """Ranges of a camera ``sensor.yaml``: focal lengths > 0, principal point inside the image, rate > 0.

    Raises:
        ValueError: Naming the file, the field and the value.
    """
    fu, fv, cu, cv = intrinsics
    width, height = resolution
    if not (fu > 0.0 and fv > 0.0):
        raise _range_error(path, "intrinsics", [fu, fv, cu, cv], "needs focal lengths fu, fv > 0 px")
    if not (-0.5 <= cu <= width - 0.5 and -0.5 <= cv <= height - 0.5):
        rule = f"needs the principal point cu, cv inside the {width}x{height} image"
        raise _range_error(path, "intrinsics", [fu, fv, cu, cv], rule)
    if not rate_hz > 0.0:
        raise _range_error(path, "rate_hz", rate_hz, "must be > 0 Hz")
    if not abs(timeshift_s) <= MAX_TIMESHIFT_S:
        raise _range_error(path, "timeshift_cam_imu", timeshift_s, f"must be within +-{MAX_TIMESHIFT_S} s")


def check_imu_ranges(path: Path, densities: dict[str, float], rate_hz: float) -> None:
    """Ranges of an IMU ``sensor.yaml``: noise densities >= 0 (0 = a perfect sensor), rate > 0.

    Raises:
        ValueError: Naming the file, the field and the value.
    """
    for field, value in densities.items():
        if not value >= 0.0:
            raise _range_error(path, field, value, "must be >= 0 (a noise density)")
    if not rate_hz > 0.0:
        raise _range_error(path, "rate_hz", rate_hz, "must be > 0 Hz")


@dataclass(frozen=True)
class ImuGap:
    """A stretch of ``imu0/data.csv`` longer than the tolerance between two consecutive samples.

    Attributes:
        index: Index of the sample before the gap (the next one is ``index + 1``).
        t0_s: Time of the sample before the gap (s, IMU clock).
        t1_s: Time of the sample after it (s).
        line0: 1-based line of the sample before the gap in ``imu0/data.csv`` (0 when unknown).
        line1: Line of the sample after it.
    """

    index: int
    t0_s: float
    t1_s: float
    line0: int = 0
    line1: int = 0

    @property
    def length_s(self) -> float:
        """Gap length (s)."""
        return self.t1_s - self.t0_s

    def describe(self, path: Path) -> str:
        """``"FILE, lines A-B: 1.000 s without IMU samples (t 1.0050 s to 2.0050 s)"``."""
        return (
            f"{path}, lines {self.line0}-{self.line1}: {self.length_s:.3f} s without IMU samples "
            f"(t {self.t0_s:.4f} s to {self.t1_s:.4f} s)"
        )


def _line_numbers(path: Path, stamps_ns: set[int]) -> dict[int, int]:
    """1-based line of each stamp in ``stamps_ns`` (read again only when a gap was found)."""
    found: dict[int, int] = {}
    with path.open("r") as handle:
        for line_no, line in enumerate(handle, start=1):
            head = line.split(",", 1)[0].strip()
            if head.isdigit() and int(head) in stamps_ns:
                found[int(head)] = line_no
    return found


def find_imu_gaps(path: Path, t_ns: np.ndarray, rate_hz: float, tolerance_periods: float) -> list[ImuGap]:
    """Gaps between consecutive IMU stamps longer than ``tolerance_periods`` nominal periods.

    Args:
        path: The ``imu0/data.csv`` the stamps come from (for line numbers).
        t_ns: IMU stamps (ns), strictly increasing.
        rate_hz: Nominal rate from ``imu0/sensor.yaml`` (Hz).
        tolerance_periods: Gaps up to this many nominal periods are normal jitter or a dropped sample.
    """
    limit_ns = tolerance_periods * 1e9 / rate_hz
    idx = np.flatnonzero(np.diff(t_ns) > limit_ns)
    if not idx.size:
        return []
    lines = _line_numbers(path, {int(t_ns[i]) for i in idx} | {int(t_ns[i + 1]) for i in idx})
    return [
        ImuGap(
            int(i),
            float(t_ns[i]) * 1e-9,
            float(t_ns[i + 1]) * 1e-9,
            lines.get(int(t_ns[i]), 0),
            lines.get(int(t_ns[i + 1]), 0),
        )
        for i in idx
    ]


def bridge_imu_gaps(
    t_s: np.ndarray, values: np.ndarray, gaps: list[ImuGap], rate_hz: float
) -> tuple[np.ndarray, np.ndarray, list[int]]:
    """Fill each gap with samples at the nominal rate, linearly interpolated between its two ends.

    Args:
        t_s: Sample times (s), shape (N,).
        values: Readings (gyro and accelerometer side by side), shape (N, 6).
        gaps: From :func:`find_imu_gaps` on the same stamps.
        rate_hz: Nominal rate (Hz).

    Returns:
        ``(t_s, values, inserted)`` with the new samples in place; ``inserted[k]`` counts those of gap k.
    """
    t_parts, v_parts, start, inserted = [], [], 0, []
    for gap in gaps:
        i = gap.index
        t_new = np.arange(t_s[i] + 1.0 / rate_hz, t_s[i + 1] - 0.5 / rate_hz, 1.0 / rate_hz)
        a = ((t_new - t_s[i]) / (t_s[i + 1] - t_s[i]))[:, None]
        t_parts += [t_s[start : i + 1], t_new]
        v_parts += [values[start : i + 1], (1.0 - a) * values[i] + a * values[i + 1]]
        start = i + 1
        inserted.append(len(t_new))
    t_parts.append(t_s[start:])
    v_parts.append(values[start:])
    return np.concatenate(t_parts), np.concatenate(v_parts), inserted
