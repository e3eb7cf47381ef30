"""The flight log of ``viotb fly``: per control tick and per frame records as growable float arrays.

One row of 25 float64 per control tick (250 Hz: 50 kB per flown second) and a phase code, instead of
ten small numpy arrays and list cells per tick (0.34 MB per flown second). Rows fill fixed-size chunks, so
the log grows without ever copying itself; readers get read-only arrays of the filled rows
(``log.p_true_W`` is (N, 3), ``log.t_s`` (N,)), so plots and metrics read the same values.
"""

from __future__ import annotations

import numpy as np

_TICK_COLUMNS = (
    ("t_s", 1),
    ("p_true_W", 3),
    ("p_est_W", 3),
    ("p_sigma_W", 3),
    ("p_set_W", 3),
    ("yaw_true", 1),
    ("yaw_est", 1),
    ("thrusts_N", 4),
    ("gyro_B", 3),
    ("accel_B", 3),
)


def _slices(columns: tuple[tuple[str, int], ...]) -> dict[str, int | slice]:
    out, start = {}, 0
    for name, width in columns:
        out[name] = start if width == 1 else slice(start, start + width)
        start += width
    return out


_TICK_SLICES = _slices(_TICK_COLUMNS)
_TICK_WIDTH = sum(w for _, w in _TICK_COLUMNS)


class _Rows:
    """Rows of ``width`` float64 in fixed-size chunks: growing never copies what is already stored."""

    def __init__(self, width: int, chunk_rows: int = 4096) -> None:
        self._width = width
        self._chunk_rows = chunk_rows
        self._chunks: list[np.ndarray] = []
        self.n = 0

    def next_row(self) -> np.ndarray:
        k = self.n % self._chunk_rows
        if k == 0:
            self._chunks.append(np.empty((self._chunk_rows, self._width)))
        self.n += 1
        return self._chunks[-1][k]

    def column(self, key: int | slice) -> np.ndarray:
        """The filled rows of one column (a read-only view for one chunk, else a read-only copy)."""
        if not self._chunks:
            out = np.empty((0, self._width))[:, key]
        elif len(self._chunks) == 1:
            out = self._chunks[0][: self.n, key]
        else:
            out = np.concatenate([c[:, key] for c in self._chunks])[: self.n]
        out.flags.writeable = False
        return out


class FlightLog:
    """Per control tick and per frame records of one flight (read-only array views).

    Tick attributes (one row per control tick): ``t_s`` (N,) s, ``phase`` (N,) names, ``p_true_W``,
    ``p_est_W``, ``p_sigma_W``, ``p_set_W`` (N, 3) m (estimate and setpoint mapped to the truth frame; NaN
    before the gauge is fixed), ``yaw_true``, ``yaw_est`` (N,) rad, ``thrusts_N`` (N, 4), ``gyro_B`` (N, 3)
    rad/s and ``accel_B`` (N, 3) m/s^2 (the newest IMU sample). Frame attributes: ``frame_t_s`` (F,) s,
    ``frame_features`` (F,) tracked features, ``frame_conditions`` (list of F tuples of condition names).
    """

    def __init__(self) -> None:
        """Create an empty log."""
        self._ticks = _Rows(_TICK_WIDTH)
        self._phase_codes = np.empty(4096, dtype=np.int8)
        self._phase_names: list[str] = []
        self._frames = _Rows(2, 1024)
        self.frame_conditions: list[tuple[str, ...]] = []

    def __len__(self) -> int:
        """Number of control ticks logged."""
        return self._ticks.n

    def append_tick(self, t_s: float, phase: str, **values) -> None:
        """Add one control tick.

        ``values`` holds every tick column but ``t_s``: an array, or a float for the whole column (NaN
        before the gauge is fixed).

        Raises:
            KeyError: A missing column.
        """
        k = self._ticks.n
        cells = [float(t_s)]
        for name, width in _TICK_COLUMNS[1:]:
            v = values[name]
            if isinstance(v, np.ndarray) and v.ndim:
                cells.extend(v.tolist())  # one row assignment below: faster than ten slice writes
            else:
                cells.extend([float(v)] * width)
        self._ticks.next_row()[:] = cells
        if k == self._phase_codes.shape[0]:
            self._phase_codes = np.concatenate([self._phase_codes, np.empty_like(self._phase_codes)])
        if phase not in self._phase_names:
            self._phase_names.append(phase)
        self._phase_codes[k] = self._phase_names.index(phase)

    def append_frame(self, t_s: float, tracked_features: int, conditions: tuple[str, ...]) -> None:
        """Add one delivered camera frame."""
        row = self._frames.next_row()
        row[0], row[1] = t_s, tracked_features
        self.frame_conditions.append(conditions)

    @property
    def phase(self) -> np.ndarray:
        """Flight phase of each tick (object array of names), shape (N,)."""
        names = np.asarray(self._phase_names + [""], dtype=object)
        return names[self._phase_codes[: self._ticks.n]]

    @property
    def frame_t_s(self) -> np.ndarray:
        """Delivery time (s) of each frame, shape (F,)."""
        return self._frames.column(0)

    @property
    def frame_features(self) -> np.ndarray:
        """Tracked features of each frame (integers stored as float), shape (F,)."""
        return self._frames.column(1)

    def __getattr__(self, name: str) -> np.ndarray:
        """The tick columns (``t_s``, ``p_true_W``, ...) as read-only views of the filled rows."""
        key = _TICK_SLICES.get(name)
        if key is None or name.startswith("_"):
            raise AttributeError(f"FlightLog has no attribute {name!r}")
        return self._ticks.column(key)
