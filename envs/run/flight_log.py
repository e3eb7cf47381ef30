"""The flight log of ``viotb fly``: per control tick and per frame records, streamed to disk in chunks.

One row of 25 float64 per control tick (250 Hz: 50 kB per flown second) and a phase code. Rows fill a
fixed-size chunk in memory (4096 rows, 16 s of flight); a full chunk is appended to an unnamed temporary
file and the buffer is reused, so a 10-minute flight holds the same memory as a 1-minute one (the phase
codes, 1 byte per tick, and the 20 Hz frame records stay in memory). ``FlightLog(in_memory=True)`` keeps
every chunk in memory instead, with the same values. Readers get read-only arrays of the filled rows
(``log.p_true_W`` is (N, 3), ``log.t_s`` (N,)), or one chunk at a time (:meth:`FlightLog.tick_chunks`),
which is how the flight's metrics are computed (:mod:`viotb.envs.run.flight_metrics`).
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path

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
    """Rows of ``width`` float64 in fixed-size chunks: one chunk in memory, the full ones in a temp file.

    Args:
        width: Floats per row.
        chunk_rows: Rows per chunk.
        in_memory: Keep full chunks in memory (a list) instead of the file.
        spill_dir: Directory of the temporary file (the system's temp directory when None).
    """

    def __init__(
        self, width: int, chunk_rows: int = 4096, in_memory: bool = False, spill_dir: Path | None = None
    ) -> None:
        self._width = width
        self._chunk_rows = chunk_rows
        self._in_memory = in_memory
        self._spill_dir = spill_dir
        self._full: list[np.ndarray] = []  # in memory only
        self._file = None  # opened on the first full chunk
        self._n_full = 0
        self._buf = np.empty((chunk_rows, width))
        self.n = 0

    def spills_next(self) -> bool:
        """Whether :meth:`next_row` will first move the full current chunk out."""
        return self.n > 0 and self.n == (self._n_full + 1) * self._chunk_rows

    def row(self, index: int) -> np.ndarray:
        """Row ``index`` (counted from the first) of the current chunk, writable, shape (width,)."""
        k = index - self._n_full * self._chunk_rows
        if not 0 <= k < min(self.n - self._n_full * self._chunk_rows, self._chunk_rows):
            raise IndexError(f"row {index} is not in the current chunk")
        return self._buf[k]

    def next_row(self) -> np.ndarray:
        """The next row to fill, shape (width,) (a view into the current chunk)."""
        k = self.n - self._n_full * self._chunk_rows
        if k == self._chunk_rows:
            self._spill()
            k = 0
        self.n += 1
        return self._buf[k]

    def _spill(self) -> None:
        """Move the full current chunk to the list or the end of the file."""
        if self._in_memory:
            self._full.append(self._buf)
            self._buf = np.empty_like(self._buf)
        else:
            if self._file is None:
                self._file = tempfile.TemporaryFile(prefix="viotb_flight_log_", dir=self._spill_dir)
            self._file.seek(0, 2)
            self._file.write(memoryview(self._buf))
        self._n_full += 1

    def _full_chunk(self, i: int) -> np.ndarray:
        if self._in_memory:
            return self._full[i]
        out = np.empty((self._chunk_rows, self._width))
        self._file.flush()
        self._file.seek(i * out.nbytes)
        if self._file.readinto(memoryview(out)) != out.nbytes:
            raise OSError(f"flight log temp file {self._file.name}: chunk {i} is short")
        return out

    def chunks(self) -> Iterator[np.ndarray]:
        """The filled rows chunk by chunk, shape (<= chunk_rows, width) each, read-only."""
        for i in range(self._n_full):
            out = self._full_chunk(i)
            out.flags.writeable = False
            yield out
        tail = self._buf[: self.n - self._n_full * self._chunk_rows]
        if tail.shape[0] or self.n == 0:
            tail = tail.view()
            tail.flags.writeable = False
            yield tail

    def column(self, key: int | slice) -> np.ndarray:
        """The filled rows of one column (a read-only view for one chunk, else a read-only copy)."""
        parts = [c[:, key] for c in self.chunks()]
        out = parts[0] if len(parts) == 1 else np.concatenate(parts)
        out.flags.writeable = False
        return out


class FlightLog:
    """Per control tick and per frame records of one flight (read-only arrays).

    Tick attributes (one row per control tick): ``t_s`` (N,) s, ``phase`` (N,) names, ``p_true_W``,
    ``p_est_W``, ``p_sigma_W``, ``p_set_W`` (N, 3) m (estimate and setpoint mapped to the truth frame; NaN
    before the gauge is fixed), ``yaw_true``, ``yaw_est`` (N,) rad, ``thrusts_N`` (N, 4), ``gyro_B`` (N, 3)
    rad/s and ``accel_B`` (N, 3) m/s^2 (the newest IMU sample). Frame attributes: ``frame_t_s`` (F,) s,
    ``frame_features`` (F,) tracked features, ``frame_conditions`` (list of F tuples of condition names).

    Args:
        in_memory: Keep every tick in memory instead of streaming full chunks to a temporary file.
        spill_dir: Directory of the temporary file (the system's temp directory when None).
        chunk_rows: Ticks per chunk (4096: 16 s at 250 Hz, 0.8 MB).
    """

    def __init__(
        self, in_memory: bool = False, spill_dir: Path | None = None, chunk_rows: int = 4096
    ) -> None:
        """Create an empty log."""
        if chunk_rows < 1:
            raise ValueError(f"chunk_rows must be positive, got {chunk_rows}")
        self._ticks = _Rows(_TICK_WIDTH, chunk_rows, in_memory, spill_dir)
        self._phase_codes = np.empty(4096, dtype=np.int8)
        self._phase_names: list[str] = []
        self._phase_index: dict[str, int] = {}
        self._frames = _Rows(2, 1024, in_memory=True)
        self.frame_conditions: list[tuple[str, ...]] = []
        self._deferred: list[tuple[int, int | slice, Callable[[], Sequence[float]]]] = []

    def __len__(self) -> int:
        """Number of control ticks logged."""
        return self._ticks.n

    def append_tick(self, t_s: float, phase: str, **values) -> None:
        """Add one control tick.

        ``values`` holds every tick column but ``t_s``: an array or a tuple of the column's width, or a
        float for the whole column (NaN before the gauge is fixed).

        Raises:
            KeyError: A missing column.
            ValueError: A column with the wrong number of values.
        """
        cells = [float(t_s)]
        for name, width in _TICK_COLUMNS[1:]:
            v = values[name]
            if isinstance(v, np.ndarray) and v.ndim:
                v = v.tolist()
            if isinstance(v, list | tuple):
                if len(v) != width:
                    raise ValueError(f"FlightLog.append_tick: {name} has {len(v)} values, expected {width}")
                cells.extend(v)
            else:
                cells.extend([float(v)] * width)
        self.append_row(phase, cells)

    def append_row(
        self,
        phase: str,
        row: list[float],
        deferred: tuple[str, Callable[[], Sequence[float]]] | None = None,
    ) -> None:
        """Add one control tick from its 25 floats in column order (``t_s``, ``p_true_W``... ``accel_B``).

        The flight runner's per-tick path (:meth:`append_tick` without the per-column dispatch): one row
        assignment into the current chunk.

        Args:
            phase: Flight phase name.
            row: The 25 values.
            deferred: ``(column name, fn)``: that column's cells are ``fn()``, called later, in order, by
                :meth:`resolve_deferred` (before any read and before the row's chunk leaves memory), so
                that values computed lazily (the estimate's covariance) are computed in one batch.

        Raises:
            ValueError: A row that is not 25 values long.
        """
        if len(row) != _TICK_WIDTH:
            raise ValueError(f"FlightLog.append_row: {len(row)} values, expected {_TICK_WIDTH}")
        if self._deferred and self._ticks.spills_next():
            self.resolve_deferred()
        k = self._ticks.n
        self._ticks.next_row()[:] = row
        if deferred is not None:
            self._deferred.append((k, _TICK_SLICES[deferred[0]], deferred[1]))
        if k == self._phase_codes.shape[0]:
            self._phase_codes = np.concatenate([self._phase_codes, np.empty_like(self._phase_codes)])
        code = self._phase_index.get(phase)
        if code is None:
            code = self._phase_index[phase] = len(self._phase_names)
            self._phase_names.append(phase)
        self._phase_codes[k] = code

    def resolve_deferred(self) -> None:
        """Fill the cells of every deferred column (see :meth:`append_row`), oldest row first."""
        pending, self._deferred = self._deferred, []
        for k, key, fn in pending:
            self._ticks.row(k)[key] = fn()

    def append_frame(self, t_s: float, tracked_features: int, conditions: tuple[str, ...]) -> None:
        """Add one delivered camera frame."""
        row = self._frames.next_row()
        row[0], row[1] = t_s, tracked_features
        self.frame_conditions.append(conditions)

    def tick_chunks(self, *names: str) -> Iterator[tuple[np.ndarray, ...]]:
        """The named tick columns one chunk of ticks at a time, in order (read-only views of one chunk).

        Args:
            names: Tick column names (``"t_s"``, ``"p_true_W"``, ...).

        Yields:
            One tuple per chunk: the columns in the order of ``names``, (n,) or (n, width) each.

        Raises:
            AttributeError: An unknown column name (raised before the first chunk).
        """
        keys = [self._tick_key(name) for name in names]
        self.resolve_deferred()
        for chunk in self._ticks.chunks():
            yield tuple(chunk[:, key] for key in keys)

    @staticmethod
    def _tick_key(name: str) -> int | slice:
        key = _TICK_SLICES.get(name)
        if key is None or name.startswith("_"):
            raise AttributeError(f"FlightLog has no attribute {name!r}")
        return key

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
        """The tick columns (``t_s``, ``p_true_W``, ...) as read-only arrays of the filled rows."""
        if name.startswith("_"):
            raise AttributeError(f"FlightLog has no attribute {name!r}")
        key = self._tick_key(name)
        self.resolve_deferred()
        return self._ticks.column(key)
