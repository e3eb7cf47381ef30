"""Keyframes, edges and closures to and from the flat arrays of :mod:`viotb.vio.loop.map_io`."""

from __future__ import annotations

import numpy as np
from viotb.vio.loop.keyframes import Keyframe
from viotb.vio.loop.pose_graph import Edge4Dof
from viotb.vio.loop.records import LoopClosure


def map_arrays(
    keyframes: list[Keyframe],
    vocabulary: np.ndarray,
    heading_axis_B: np.ndarray,
    edges: list[Edge4Dof],
    closures: list[LoopClosure],
) -> dict[str, np.ndarray]:
    """Flat arrays of localized keyframes (their map poses set), the edges among them, and the closures.

    Keyframes are renumbered 0..K-1 in the given order; edges touching a keyframe not given are dropped.
    """
    row_of = {kf.index: r for r, kf in enumerate(keyframes)}
    counts = [len(kf.descriptors) for kf in keyframes]
    kept = [e for e in edges if e.i in row_of and e.j in row_of]

    def stack(items, shape, dtype):
        return np.array(items, dtype=dtype).reshape(shape)

    return {
        "kf_t_s": stack([kf.t_s for kf in keyframes], (-1,), np.float64),
        "kf_sequence": stack([kf.sequence for kf in keyframes], (-1,), np.int64),
        "kf_R_WB_odom": stack([kf.R_WB_odom for kf in keyframes], (-1, 3, 3), np.float64),
        "kf_p_WB_odom": stack([kf.p_WB_odom for kf in keyframes], (-1, 3), np.float64),
        "kf_R_WB_map": stack([kf.R_WB_map for kf in keyframes], (-1, 3, 3), np.float64),
        "kf_p_WB_map": stack([kf.p_WB_map for kf in keyframes], (-1, 3), np.float64),
        "kf_feature_start": np.concatenate([[0], np.cumsum(counts)]).astype(np.int64),
        "keypoints_uv_px": np.vstack([np.zeros((0, 2))] + [kf.keypoints_uv_px for kf in keyframes]).astype(
            np.float32
        ),
        "descriptors": np.vstack([np.zeros((0, 32))] + [kf.descriptors for kf in keyframes]).astype(np.uint8),
        "landmarks_B": np.vstack([np.zeros((0, 3))] + [kf.landmarks_B for kf in keyframes]).astype(
            np.float64
        ),
        "keypoint_octave": np.concatenate(
            [np.zeros(0, dtype=np.int8)]
            + [
                np.zeros(len(kf.descriptors), np.int8) if kf.octaves is None else kf.octaves
                for kf in keyframes
            ]
        ).astype(np.int8),
        "vocabulary": np.asarray(vocabulary, dtype=np.uint8),
        "heading_axis_B": np.asarray(heading_axis_B, dtype=np.float64),
        "edge_ij": stack([(row_of[e.i], row_of[e.j]) for e in kept], (-1, 2), np.int64),
        "edge_dyaw_rad": stack([e.dyaw_rad for e in kept], (-1,), np.float64),
        "edge_dp_m": stack([e.dp_m for e in kept], (-1, 3), np.float64),
        "edge_is_loop": stack([e.is_loop for e in kept], (-1,), bool),
        "closure_t_s": stack([(c.t_query_s, c.t_match_s) for c in closures], (-1, 2), np.float64),
        "closure_p_xyz": stack([c.p_xyz for c in closures], (-1, 3), np.float64),
        "closure_quat_xyzw": stack([c.quat_xyzw for c in closures], (-1, 4), np.float64),
        "closure_inliers": stack([c.inliers for c in closures], (-1,), np.int64),
    }


def keyframes_from_arrays(
    arrays: dict[str, np.ndarray],
) -> tuple[list[Keyframe], list[Edge4Dof], list[LoopClosure]]:
    """Inverse of :func:`map_arrays`: keyframes (index = row), edges and closures."""
    start = arrays["kf_feature_start"]
    octaves = arrays.get("keypoint_octave")
    keyframes = []
    for k in range(len(arrays["kf_t_s"])):
        rows = slice(int(start[k]), int(start[k + 1]))
        keyframes.append(
            Keyframe(
                index=k,
                t_s=float(arrays["kf_t_s"][k]),
                sequence=int(arrays["kf_sequence"][k]),
                R_WB_odom=arrays["kf_R_WB_odom"][k].copy(),
                p_WB_odom=arrays["kf_p_WB_odom"][k].copy(),
                keypoints_uv_px=arrays["keypoints_uv_px"][rows].copy(),
                descriptors=np.ascontiguousarray(arrays["descriptors"][rows]),
                landmarks_B=arrays["landmarks_B"][rows].copy(),
                R_WB_map=arrays["kf_R_WB_map"][k].copy(),
                p_WB_map=arrays["kf_p_WB_map"][k].copy(),
                octaves=None if octaves is None else octaves[rows].copy(),
            )
        )
    edges = [
        Edge4Dof(int(i), int(j), float(dyaw), dp.copy(), bool(loop))
        for (i, j), dyaw, dp, loop in zip(
            arrays["edge_ij"],
            arrays["edge_dyaw_rad"],
            arrays["edge_dp_m"],
            arrays["edge_is_loop"],
            strict=True,
        )
    ]
    closures = [
        LoopClosure(float(t[0]), float(t[1]), p.copy(), q.copy(), int(n))
        for t, p, q, n in zip(
            arrays["closure_t_s"],
            arrays["closure_p_xyz"],
            arrays["closure_quat_xyzw"],
            arrays["closure_inliers"],
            strict=True,
        )
    ]
    return keyframes, edges, closures
