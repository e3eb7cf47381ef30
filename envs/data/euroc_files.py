"""Low-level readers of EuRoC ASL files: ``sensor.yaml`` mappings and numeric CSVs, with located errors.

Every error names the file, the line (for CSVs) or the field (for YAML) and the offending value. Used by the
dataset reader (:mod:`.euroc`) and the ground-truth sources (:mod:`.euroc_truth`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import yaml


def require_file(path: Path) -> Path:
    """``path`` if it is a file, else FileNotFoundError naming it."""
    if not path.is_file():
        raise FileNotFoundError(f"missing EuRoC file: {path}")
    return path


class _SensorYamlLoader(yaml.SafeLoader):
    """PyYAML's safe loader that also reads OpenCV's ``!!opencv-matrix`` tag (a mapping with ``data``)."""


_SensorYamlLoader.add_constructor(
    "tag:yaml.org,2002:opencv-matrix", lambda loader, node: loader.construct_mapping(node, deep=True)
)


def read_yaml(path: Path) -> dict:
    """Parse a sensor.yaml, tolerating OpenCV's ``%YAML:1.0`` first line and ``!!opencv-matrix`` tags."""
    text = require_file(path).read_text()
    lines = text.splitlines()
    if lines and lines[0].startswith("%YAML"):
        lines = lines[1:]
    try:
        data = yaml.load("\n".join(lines), Loader=_SensorYamlLoader)  # a SafeLoader subclass
    except yaml.YAMLError as exc:
        raise ValueError(f"{path}: malformed YAML: {exc}") from None
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a YAML mapping, got {type(data).__name__}")
    return data


def yaml_field(data: dict, path: Path, key: str, length: int | None = None) -> object:
    """Field ``key`` of a parsed ``sensor.yaml``; with ``length``, a list of that many finite floats.

    Raises:
        ValueError: Missing field, wrong count, non-number or non-finite value (names file, field, value).
    """
    if key not in data:
        raise ValueError(f"{path}: missing field {key!r}")
    value = data[key]
    if isinstance(value, dict) and "data" in value and length is not None:
        value = value["data"]  # an OpenCV matrix (``!!opencv-matrix``) holding the list
    if length is not None:
        if not isinstance(value, list) or len(value) != length:
            raise ValueError(f"{path}: field {key!r} must be a list of {length} numbers, got {value!r}")
        try:
            value = [float(v) for v in value]
        except (TypeError, ValueError):
            raise ValueError(f"{path}: field {key!r} must hold numbers, got {data[key]!r}") from None
        if not all(np.isfinite(value)):
            raise ValueError(f"{path}: field {key!r} has non-finite values: {value!r}")
    return value


def yaml_number(data: dict, path: Path, key: str) -> float:
    """Field ``key`` as one finite float (ValueError naming file, field and value otherwise)."""
    value = yaml_field(data, path, key)
    try:
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise ValueError(f"{path}: field {key!r} must be a number, got {value!r}") from None
    if not np.isfinite(number):
        raise ValueError(f"{path}: field {key!r} must be finite, got {value!r}")
    return number


def read_T_BS(data: dict, path: Path) -> np.ndarray:
    """The ``T_BS`` field (4, 4) of a parsed ``sensor.yaml``: sensor frame S in the body (IMU) frame B.

    Raises:
        ValueError: Missing or malformed, a rotation block that is not a rotation, or a last row other than
            ``[0, 0, 0, 1]`` (the message names the file and the value).
    """
    t_bs = yaml_field(data, path, "T_BS")
    if not isinstance(t_bs, dict):
        raise ValueError(f"{path}: field 'T_BS' must be a mapping with 'data', got {t_bs!r}")
    T = np.array(yaml_field(t_bs, path, "data", 16)).reshape(4, 4)  # type: ignore[arg-type]
    R = T[:3, :3]
    if not np.allclose(R.T @ R, np.eye(3), atol=1e-5) or np.linalg.det(R) < 0.0:
        raise ValueError(f"{path}: T_BS rotation block is not a rotation matrix: {R.tolist()}")
    if not np.allclose(T[3], [0.0, 0.0, 0.0, 1.0]):
        raise ValueError(f"{path}: T_BS last row must be [0, 0, 0, 1], got {T[3].tolist()}")
    return T


def read_rows(path: Path, n_cols: int) -> tuple[list[int], list[list[str]]]:
    """Data rows of a EuRoC CSV as (1-based line numbers, stripped fields); checks the column count."""
    line_numbers: list[int] = []
    rows: list[list[str]] = []
    with require_file(path).open("r", newline="") as handle:
        for line_no, line in enumerate(handle, start=1):
            text = line.strip()
            if not text or text.startswith("#"):
                continue
            fields = [f.strip() for f in text.split(",")]
            if len(fields) != n_cols:
                raise ValueError(
                    f"{path}, line {line_no}: expected {n_cols} comma-separated values, "
                    f"got {len(fields)}: {text!r}"
                )
            line_numbers.append(line_no)
            rows.append(fields)
    if not rows:
        raise ValueError(f"{path}: no data rows")
    return line_numbers, rows


def parse_ns(path: Path, line_numbers: list[int], column: list[str]) -> np.ndarray:
    """Integer-ns stamps (N,) of a CSV column; they must strictly increase (ValueError names the lines)."""
    out = np.empty(len(column), dtype=np.int64)
    for i, text in enumerate(column):
        try:
            out[i] = int(text)
        except ValueError:
            raise ValueError(
                f"{path}, line {line_numbers[i]}: timestamp must be an integer (ns), got {text!r}"
            ) from None
    diffs = np.diff(out)
    bad = np.flatnonzero(diffs <= 0)
    if bad.size:
        i = int(bad[0])
        kind = "duplicate" if diffs[i] == 0 else "non-monotonic"
        raise ValueError(
            f"{path}, lines {line_numbers[i]}-{line_numbers[i + 1]}: {kind} timestamps "
            f"{out[i]} then {out[i + 1]} (must strictly increase)"
        )
    return out


def parse_floats(path: Path, line_numbers: list[int], rows: list[list[str]]) -> np.ndarray:
    """Finite floats (N, K) of CSV rows (ValueError names the line, column and text otherwise)."""
    out = np.empty((len(rows), len(rows[0])))
    for i, row in enumerate(rows):
        for j, text in enumerate(row):
            try:
                value = float(text)
            except ValueError:
                where = f"{path}, line {line_numbers[i]}, column {j + 2}"
                raise ValueError(f"{where}: not a number: {text!r}") from None
            if not np.isfinite(value):
                raise ValueError(f"{path}, line {line_numbers[i]}, column {j + 2}: non-finite value {text!r}")
            out[i, j] = value
    return out


def read_numeric_csv(path: Path, n_cols: int) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps ns (N,), values (N, n_cols - 1)) of a numeric EuRoC CSV."""
    line_numbers, rows = read_rows(path, n_cols)
    t_ns = parse_ns(path, line_numbers, [r[0] for r in rows])
    values = parse_floats(path, line_numbers, [r[1:] for r in rows])
    return t_ns, values


def ns_to_s(t_ns: np.ndarray) -> np.ndarray:
    """Integer nanoseconds (N,) to float64 seconds (N,)."""
    return t_ns.astype(np.float64) * 1e-9
