"""Maps on disk: one ``.npz`` of plain arrays plus a JSON header, read with ``allow_pickle=False``.

Arrays (K keyframes, N features in all, E edges, L closures):

- ``kf_t_s`` (K,), ``kf_sequence`` (K,) int64, ``kf_R_WB_odom`` (K, 3, 3), ``kf_p_WB_odom`` (K, 3),
  ``kf_R_WB_map`` (K, 3, 3), ``kf_p_WB_map`` (K, 3) in the map frame (m);
- ``kf_feature_start`` (K + 1,) int64: keyframe k owns feature rows ``[start[k], start[k + 1])``;
- ``keypoints_uv_px`` (N, 2) float32, ``descriptors`` (N, 32) uint8, ``landmarks_B`` (N, 3) float64 (NaN:
none); optionally ``keypoint_octave`` (N,) int8, the ORB pyramid level of each feature (a map written
  before it existed reads as all level 0);
- ``vocabulary`` (W, 32) uint8; ``heading_axis_B`` (3,): the body axis whose heading is the yaw;
- ``edge_ij`` (E, 2) int64 keyframe rows, ``edge_dyaw_rad`` (E,), ``edge_dp_m`` (E, 3), ``edge_is_loop``
(E,) bool;
- ``closure_t_s`` (L, 2) query and match times, ``closure_p_xyz`` (L, 3), ``closure_quat_xyzw`` (L, 4),
  ``closure_inliers`` (L,) int64;
- ``header_json``: a 0-d unicode array, ``{"format": "viotb-loop-map", "version": 1}``.
"""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np

MAP_FORMAT = "viotb-loop-map"
MAP_VERSION = 1
MAP_KEYS = (
    "kf_t_s",
    "kf_sequence",
    "kf_R_WB_odom",
    "kf_p_WB_odom",
    "kf_R_WB_map",
    "kf_p_WB_map",
    "kf_feature_start",
    "keypoints_uv_px",
    "descriptors",
    "landmarks_B",
    "vocabulary",
    "heading_axis_B",
    "edge_ij",
    "edge_dyaw_rad",
    "edge_dp_m",
    "edge_is_loop",
    "closure_t_s",
    "closure_p_xyz",
    "closure_quat_xyzw",
    "closure_inliers",
)
MAP_OPTIONAL_KEYS = ("keypoint_octave",)


def write_map_arrays(path: Path | str, arrays: dict[str, np.ndarray]) -> None:
    """Write the map arrays atomically (temporary file, then rename).

    Raises:
        KeyError: A key of ``MAP_KEYS`` is missing.
    """
    missing = [k for k in MAP_KEYS if k not in arrays]
    if missing:
        raise KeyError(f"map arrays miss {missing}")
    path = Path(path)
    header = json.dumps({"format": MAP_FORMAT, "version": MAP_VERSION})
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".npz")
    os.close(fd)
    try:
        with open(tmp, "wb") as f:
            keys = MAP_KEYS + tuple(k for k in MAP_OPTIONAL_KEYS if k in arrays)
            np.savez_compressed(f, header_json=np.array(header), **{k: arrays[k] for k in keys})
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def read_map_arrays(path: Path | str) -> dict[str, np.ndarray]:
    """Read map arrays written by :func:`write_map_arrays`.

    Raises:
        FileNotFoundError: No such file.
        ValueError: Not a map of this format or version, or inconsistent sizes.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"map file not found: {path}")
    with np.load(path, allow_pickle=False) as data:
        header = json.loads(str(data["header_json"]))
        if header.get("format") != MAP_FORMAT or header.get("version") != MAP_VERSION:
            raise ValueError(f"{path}: not a {MAP_FORMAT} v{MAP_VERSION} file (header {header})")
        arrays = {k: data[k] for k in MAP_KEYS + MAP_OPTIONAL_KEYS if k in data or k in MAP_KEYS}
    start = arrays["kf_feature_start"]
    if len(start) != len(arrays["kf_t_s"]) + 1 or start[-1] != len(arrays["descriptors"]):
        raise ValueError(f"{path}: kf_feature_start does not match the keyframe and feature counts")
    if "keypoint_octave" in arrays and len(arrays["keypoint_octave"]) != len(arrays["descriptors"]):
        raise ValueError(
            f"{path}: keypoint_octave has {len(arrays['keypoint_octave'])} rows, "
            f"descriptors {len(arrays['descriptors'])}"
        )
    return arrays
