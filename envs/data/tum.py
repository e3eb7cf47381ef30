"""TUM RGB-D trajectory files: one pose per line, ``t x y z qx qy qz qw`` (Sturm et al., IROS 2012).

Times in seconds, positions in metres, Hamilton quaternion of ``R_WB`` in x, y, z, w order (the file's
order; in memory we keep ``quat_wxyz``). Lines starting with ``#`` are comments. This is the format that
``evo_ape tum`` and the ``viotb eval`` outputs use.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from viotb.vio.types import TrajectoryArrays

TUM_HEADER = "# t x y z qx qy qz qw"


def write_tum(path: Path | str, trajectory: TrajectoryArrays) -> Path:
    """Write ``trajectory`` to ``path`` (parent folders are created); values keep full float precision.

    Raises:
        ValueError: Arrays of mismatched shapes or non-finite values.
    """
    path = Path(path)
    n = len(trajectory)
    if trajectory.p_WB.shape != (n, 3) or trajectory.quat_wxyz_WB.shape != (n, 4):
        raise ValueError(
            f"write_tum({path}): expected p_WB ({n}, 3) and quat_wxyz_WB ({n}, 4), got "
            f"{trajectory.p_WB.shape} and {trajectory.quat_wxyz_WB.shape}"
        )
    q = trajectory.quat_wxyz_WB
    table = np.column_stack([trajectory.t_s, trajectory.p_WB, q[:, 1], q[:, 2], q[:, 3], q[:, 0]])
    if not np.all(np.isfinite(table)):
        row = int(np.flatnonzero(~np.isfinite(table).all(axis=1))[0])
        raise ValueError(f"write_tum({path}): pose {row} is not finite: {table[row].tolist()}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as handle:
        handle.write(TUM_HEADER + "\n")
        handle.writelines(" ".join(repr(float(v)) for v in row) + "\n" for row in table)
    return path


def read_tum(path: Path | str) -> TrajectoryArrays:
    """Read a TUM file into :class:`TrajectoryArrays` (quaternions normalised, ``v_WB`` None).

    Raises:
        FileNotFoundError: Missing file.
        ValueError: Wrong column count, non-numbers, non-finite values, zero quaternions or times that do
            not strictly increase; the message names the file, line and value.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"TUM trajectory file not found: {path}")
    rows: list[list[float]] = []
    line_numbers: list[int] = []
    with path.open("r") as handle:
        for line_no, line in enumerate(handle, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = text.replace(",", " ").split()
            if len(fields) != 8:
                raise ValueError(f"{path}, line {line_no}: expected 8 values (t x y z qx qy qz qw): {text!r}")
            try:
                values = [float(f) for f in fields]
            except ValueError:
                raise ValueError(f"{path}, line {line_no}: not a number in {text!r}") from None
            if not all(np.isfinite(values)):
                raise ValueError(f"{path}, line {line_no}: non-finite value in {text!r}")
            rows.append(values)
            line_numbers.append(line_no)
    if not rows:
        raise ValueError(f"{path}: no poses")
    table = np.array(rows)
    bad = np.flatnonzero(np.diff(table[:, 0]) <= 0.0)
    if bad.size:
        i = int(bad[0])
        raise ValueError(
            f"{path}, lines {line_numbers[i]}-{line_numbers[i + 1]}: times must strictly increase, got "
            f"{table[i, 0]!r} then {table[i + 1, 0]!r}"
        )
    quat_wxyz = table[:, [7, 4, 5, 6]]
    norms = np.linalg.norm(quat_wxyz, axis=1)
    zero = np.flatnonzero(norms < 1e-9)
    if zero.size:
        raise ValueError(f"{path}, line {line_numbers[int(zero[0])]}: zero quaternion")
    return TrajectoryArrays(table[:, 0].copy(), table[:, 1:4].copy(), quat_wxyz / norms[:, None])
