"""Measure the KLT front end's error along each track against the exact projection of the tracked 3-D point.

For a rendered recording (``viotb record SCENARIO``): run :class:`viotb.vio.frontend.KltTracker` over every
frame; at a track's first observation cast the ray of the measured pixel from the true camera centre into the
MuJoCo scene (``mujoco.mj_ray``, the vehicle excluded), which gives the 3-D point the track started on; then
project that point with the true pose into every later frame of the track. ``e_k`` (px) is the KLT position
minus that projection, ``k`` frames after the first observation (``e_0 = 0`` by construction). The renderer
itself projects to 0.08 px, so ``e_k`` is the front end's error.

Model fitted (per image axis, in px): ``e_k = w_k - w_0 + sum_{j=1..k} u_j`` with white ``w`` (sigma
``s_w``) and a per-frame random walk ``u`` (sigma ``s_rw``). Two independent estimates:

1. Increments ``d_k = e_k - e_{k-1}``: ``var(d) = 2 s_w^2 + s_rw^2`` and ``cov(d_k, d_{k+1}) = -s_w^2``.
2. Growth ``var(e_k) = 2 s_w^2 + k s_rw^2`` for ``k >= 1`` (least squares over ``k``).

Robust (MAD) sigmas are used so that a few gross outliers (a track jumping an occluding edge) do not set the
white-noise level; their share is reported. ``core`` (:func:`fit_core`) fits the same model over the image
path in windows of up to 40 frames: the model of the tracks the MSCKF's gate keeps
(``viotb.vio.msckf_params.RENDER_KLT_PIXEL_SIGMA_PX``). Also reported: the random-walk step against the
image motion of the feature per frame (does the slide follow motion or time?).

Usage::

    python benchmarks/klt_track_error.py RECORDING_DIR SCENARIO [--max-frames N] [--json] [--anchor]
        [--projective-after-px PX] [--klt FIELD=VALUE ...]
"""

from __future__ import annotations

import argparse
import ast
import json
import os
from pathlib import Path

import numpy as np


def _mad_var(x: np.ndarray) -> float:
    """Variance from the median absolute deviation about zero (robust to a few gross errors)."""
    x = np.asarray(x, dtype=float).ravel()
    return float((1.4826 * np.median(np.abs(x))) ** 2) if x.size else float("nan")


def track_errors(
    rec: Path,
    scenario: str,
    max_frames: int | None = None,
    edge_px: float = 3.0,
    anchor: bool = False,
    projective_after_px: float = float("inf"),
    klt: dict | None = None,
) -> tuple[dict[int, np.ndarray], dict[int, float]]:
    """KLT error of every track against the true projection of its first 3-D point.

    Args:
        rec: Recording folder.
        scenario: The scenario it was recorded from (its scene is ray cast).
        max_frames: Frames to use (None: all).
        edge_px: Offset (px) of the four neighbour rays that measure the depth step around a first point.
        anchor: Track with ``KltParams.anchor_templates`` (drift correction against the first template).
        projective_after_px: ``KltParams.anchor_projective_after_px`` (homography alignment of the anchors).
        klt: Other ``KltParams`` fields (e.g. ``{"anchor_zncc_at_final_warp": True}``).

    Returns:
        ``(errors, depth_step)``: track id -> array (n, 8) of frame index, e_u, e_v (px), u, v of the KLT
        position (px), the world z of the first 3-D point (m; the floor is z = 0), the cosine of the angle
        between the current view ray and the surface normal (1: seen head on, 0: grazing; the normal from
        the four neighbour rays' points, NaN on a depth edge) and the image distance (px) from the first
        observation; and track id -> the largest relative depth difference between the first ray and its
        four neighbours ``edge_px`` away (large on an occluding contour: the corner is no 3-D point).
    """
    os.environ.setdefault("MUJOCO_GL", "egl")
    import mujoco
    from viotb.envs.data.euroc import load_image, read_euroc
    from viotb.envs.data.eval_frames import interpolate_pose
    from viotb.envs.scenarios.registry import get_scenario
    from viotb.envs.sim.simulation import Simulation
    from viotb.models.constants import VEHICLE_BODIES
    from viotb.vio.frontend import KltParams, KltTracker
    from viotb.vio.types import CameraFrame

    ds = read_euroc(rec)
    sc = get_scenario(scenario)
    sim = Simulation(sc.vehicle, sc.scene)
    body = mujoco.mj_name2id(sim.model, mujoco.mjtObj.mjOBJ_BODY, VEHICLE_BODIES[sc.vehicle])
    mujoco.mj_forward(sim.model, sim.data)
    cam = ds.calib.camera
    settings = {"anchor_templates": anchor, "anchor_projective_after_px": projective_after_px, **(klt or {})}
    trk = KltTracker(cam, KltParams(**settings))
    n = len(ds.cam_t_s) if max_frames is None else min(max_frames, len(ds.cam_t_s))
    point: dict[int, np.ndarray | None] = {}
    normal: dict[int, np.ndarray] = {}
    first_uv: dict[int, np.ndarray] = {}
    step: dict[int, float] = {}
    offsets = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]]) * edge_px / cam.fx
    out: dict[int, list] = {}
    geom = np.zeros(1, dtype=np.int32)
    for i in range(n):
        t = float(ds.cam_t_s[i])
        tracks = trk.process(CameraFrame(t_s=t, image=load_image(ds, i)), t)
        R_WB, p_WB = interpolate_pose(ds.groundtruth, t + ds.calib.time_offset_s)
        R_WC = R_WB @ ds.calib.R_BC
        p_WC = p_WB + R_WB @ ds.calib.p_BC
        for tid, xy, uv in zip(tracks.ids, tracks.xy_norm, tracks.uv_px, strict=True):
            tid = int(tid)
            if tid not in point:
                ray = R_WC @ np.array([xy[0], xy[1], 1.0])
                ray /= np.linalg.norm(ray)
                dist = mujoco.mj_ray(sim.model, sim.data, p_WC, ray, None, 1, body, geom)
                point[tid] = p_WC + dist * ray if dist > 0 else None
                out[tid] = []
                z0 = (R_WC.T @ (dist * ray))[2]
                zs, nb = [], []
                for off in offsets:
                    r2 = R_WC @ np.array([xy[0] + off[0], xy[1] + off[1], 1.0])
                    r2 /= np.linalg.norm(r2)
                    d2 = mujoco.mj_ray(sim.model, sim.data, p_WC, r2, None, 1, body, geom)
                    zs.append((R_WC.T @ (d2 * r2))[2] if d2 > 0 else np.inf)
                    nb.append(d2 * r2)
                step[tid] = float(np.max(np.abs(np.array(zs) - z0)) / max(z0, 1e-6))
                # The surface normal from the neighbours (+u, -u, +v, -v), towards the camera.
                n_W = np.cross(nb[0] - nb[1], nb[2] - nb[3])
                n_W = n_W / max(np.linalg.norm(n_W), 1e-12) * (-1.0 if n_W @ ray > 0 else 1.0)
                normal[tid] = n_W if step[tid] < 0.05 else np.full(3, np.nan)
                first_uv[tid] = np.asarray(uv, dtype=float)
            p_f = point[tid]
            if p_f is None:
                continue
            p_C = R_WC.T @ (p_f - p_WC)
            if p_C[2] <= 1e-3:
                continue
            uv_true = cam.project(p_C[None])[0]
            view = (p_f - p_WC) / np.linalg.norm(p_f - p_WC)
            cos_view = abs(float(view @ normal[tid]))
            moved = float(np.linalg.norm(uv - first_uv[tid]))
            out[tid].append((i, *(uv - uv_true), *uv, p_f[2], cos_view, moved))
    errors = {k: np.array(v) for k, v in out.items() if len(v) >= 2}
    return errors, {k: step[k] for k in errors}


def fit_noise(tracks: dict[int, np.ndarray], max_lag: int = 30) -> dict:
    """The white + random-walk model of the module docstring, fitted to the track errors."""
    d_all, d_next, motion, d_mot = [], [], [], []
    by_lag: dict[int, list] = {k: [] for k in range(1, max_lag + 1)}
    for a in tracks.values():
        if not np.all(np.diff(a[:, 0]) == 1):
            continue
        e = a[:, 1:3]
        d = np.diff(e, axis=0)
        d_all.append(d)
        if len(d) >= 2:
            d_next.append(np.stack([d[:-1], d[1:]], axis=1))
        mv = np.linalg.norm(np.diff(a[:, 3:5], axis=0), axis=1)
        motion.append(mv)
        d_mot.append(d)
        for k in range(1, min(len(e), max_lag + 1)):
            by_lag[k].append(e[k])
    d = np.concatenate(d_all)
    pairs = np.concatenate(d_next)
    var_d = _mad_var(d)
    # Robust lag-1 covariance: var(d_k + d_{k+1}) = 2 var(d) + 2 cov  ->  cov = (var(sum) - 2 var(d)) / 2.
    cov1 = 0.5 * (_mad_var(pairs[:, 0] + pairs[:, 1]) - 2.0 * var_d)
    s_w2 = max(-cov1, 0.0)
    s_rw2_inc = max(var_d - 2.0 * s_w2, 0.0)
    lags = np.array([k for k in by_lag if len(by_lag[k]) >= 30])
    var_k = np.array([_mad_var(np.array(by_lag[k])) for k in lags])
    A = np.column_stack([np.ones(len(lags)), lags.astype(float)])
    c0, slope = np.linalg.lstsq(A, var_k, rcond=None)[0]
    mv, dm = np.concatenate(motion), np.concatenate(d_mot)
    bins = [0.0, 0.5, 1.0, 2.0, 4.0, 8.0, 1e9]
    by_motion = []
    for lo, hi in zip(bins[:-1], bins[1:], strict=True):
        sel = (mv >= lo) & (mv < hi)
        if sel.sum() >= 30:
            sig = float(np.sqrt(_mad_var(dm[sel])))
            by_motion.append({"motion_px": [lo, hi], "n": int(sel.sum()), "inc_sigma_px": sig})
    gross = float(np.mean(np.linalg.norm(d, axis=1) > 3.0))
    # 3. Non-robust growth (the 0.5 % largest cut: the chi-square gate's share) from windows starting every
    #    10 frames, up to 40 frames long (what an MSCKF window sees), against frames and against image path.
    E, P, Kf = [], [], []
    for a in tracks.values():
        if not np.all(np.diff(a[:, 0]) == 1):
            continue
        for s0 in range(0, len(a) - 1, 10):
            b = a[s0 : s0 + 41]
            E.append(np.sum((b[1:, 1:3] - b[0, 1:3]) ** 2, axis=1) / 2.0)
            P.append(np.cumsum(np.linalg.norm(np.diff(b[:, 3:5], axis=0), axis=1)))
            Kf.append(np.arange(1, len(b), dtype=float))
    e2, path, kf = np.concatenate(E), np.concatenate(P), np.concatenate(Kf)
    keep = e2 < np.percentile(e2, 99.5)
    growth = {}
    for name, x in (("px2_per_frame", kf), ("px2_per_px_of_motion", path)):
        A = np.column_stack([np.ones(keep.sum()), x[keep]])
        growth[name] = float(np.linalg.lstsq(A, e2[keep], rcond=None)[0][1])
    return {
        "tracks": len(tracks),
        "increments": int(len(d)),
        "increment_sigma_px": float(np.sqrt(var_d)),
        "lag1_cov_px2": float(cov1),
        "white_sigma_px_from_increments": float(np.sqrt(s_w2)),
        "rw_sigma_px_per_frame_from_increments": float(np.sqrt(s_rw2_inc)),
        "white_sigma_px_from_growth": float(np.sqrt(max(c0, 0.0) / 2.0)),
        "rw_sigma_px_per_frame_from_growth": float(np.sqrt(max(slope, 0.0))),
        "error_sigma_px_by_lag": {int(k): float(np.sqrt(v)) for k, v in zip(lags, var_k, strict=True)},
        "increment_sigma_by_motion": by_motion,
        "gross_increment_share": gross,
        "rw_variance_growth_trimmed": growth,
        "median_image_motion_px_per_frame": float(np.median(mv)),
    }


def _segments(
    tracks: dict[int, np.ndarray], length: int = 41, every: int = 10
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Windows of consecutive views (up to ``length``, one every ``every`` views): errors against the first.

    Returns:
        A list of ``(x, path)``: ``x`` (n, 2) the error of views 1..n minus that of view 0 (px), ``path`` (n,)
        the image path (px) travelled since view 0.
    """
    out = []
    for a in tracks.values():
        if not np.all(np.diff(a[:, 0]) == 1):
            continue
        for s0 in range(0, len(a) - 1, every):
            b = a[s0 : s0 + length]
            out.append(
                (b[1:, 1:3] - b[0, 1:3], np.cumsum(np.linalg.norm(np.diff(b[:, 3:5], axis=0), axis=1)))
            )
    return out


def fit_core(tracks: dict[int, np.ndarray], tail_sigmas: float = 5.0) -> dict:
    """White + random-walk-per-px model of the typical track (robust), and the share of the tail beyond it.

    The errors are heavy tailed: most tracks follow their point to a few hundredths of a pixel, while a few
    (corners on occluding contours, which are no 3-D point, and tracks that slip) leave it by pixels; those
    the MSCKF's chi-square gate removes, so its noise model is the one of the core. In the windows of
    :func:`_segments` the error against the window's first view is ``x_k = w_k - w_0 + walk``, per axis
    ``var(x_k) = 2 s_w^2 + q p_k`` (``p_k`` the image path since the first view): the robust (MAD) variance
    of ``x`` in bins of ``p`` is fitted by non-negative least squares, weighted by the samples per bin.

    Returns:
        ``white_sigma_px``, ``rw_px2_per_px``, ``mad_sigma_px_by_path`` (bin -> robust sigma per axis),
        ``tail_share`` (samples beyond ``tail_sigmas`` model sigmas on either axis) and ``windows``.
    """
    from scipy.optimize import nnls

    segs = _segments(tracks)
    x = np.concatenate([s for s, _ in segs])
    path = np.concatenate([p for _, p in segs])
    edges = np.array([0.0, 1.0, 2.0, 4.0, 7.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, 80.0, 120.0])
    rows, by_path = [], {}
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        sel = (path >= lo) & (path < hi)
        if sel.sum() < 100:
            continue
        v = _mad_var(x[sel])
        rows.append((float(np.mean(path[sel])), v, float(np.sqrt(sel.sum()))))
        by_path[f"{lo:g}-{hi:g}"] = float(np.sqrt(v))
    p_mid, var, w = (np.array(c) for c in zip(*rows, strict=True))
    (s_w2x2, q), _ = nnls(np.column_stack([np.full(len(p_mid), 2.0), p_mid]) * w[:, None], var * w)
    sig = np.sqrt(2.0 * s_w2x2 + q * path)
    tail = float(np.mean(np.any(np.abs(x) > tail_sigmas * sig[:, None], axis=1)))
    return {
        "white_sigma_px": float(np.sqrt(s_w2x2)),
        "rw_px2_per_px": float(q),
        "mad_sigma_px_by_path": by_path,
        "tail_share": tail,
        "windows": len(segs),
    }


def bias_split(
    tracks: dict[int, np.ndarray],
    depth_step: dict[int, float],
    floor_z_m: float = 0.02,
    gross_px: float = 2.0,
) -> dict:
    """The mean track error (a bias shared by many tracks) by surface, foreshortening and view change.

    Observations of tracks off depth edges (relative depth step under 0.05) with an error under ``gross_px``
    (the tail the MSCKF's gate removes), split by the surface of the first 3-D point (floor: world z under
    ``floor_z_m``; walls and objects: the rest), by the cosine between view ray and surface normal and by
    the image distance from the first observation.

    Returns:
        ``{surface: {"by_distance_px": {bin: row}, "by_cos_view": {bin: row}}}``, a row: ``n``, ``mean_px``
        (e_u, e_v), ``median_px`` (e_u, e_v) and ``rms_px``.
    """
    rows = [a for k, a in tracks.items() if depth_step[k] < 0.05 and a.shape[1] >= 8]
    A = np.vstack(rows)
    A = A[np.linalg.norm(A[:, 1:3], axis=1) < gross_px]
    floor = np.abs(A[:, 5]) < floor_z_m

    def row(sel: np.ndarray) -> dict:
        e = A[sel, 1:3]
        return {
            "n": int(sel.sum()),
            "mean_px": [round(float(v), 4) for v in e.mean(axis=0)],
            "median_px": [round(float(v), 4) for v in np.median(e, axis=0)],
            "rms_px": round(float(np.sqrt(np.mean(e * e))), 4),
        }

    out = {}
    for name, surf in (("floor", floor), ("walls", ~floor)):
        split: dict[str, dict] = {"by_distance_px": {}, "by_cos_view": {}}
        for key, col, edges in (
            ("by_distance_px", 7, [0.0, 10.0, 30.0, 60.0, 120.0, 400.0]),
            ("by_cos_view", 6, [0.0, 0.2, 0.4, 0.6, 0.8, 1.01]),
        ):
            for lo, hi in zip(edges[:-1], edges[1:], strict=True):
                sel = surf & (A[:, col] >= lo) & (A[:, col] < hi)
                if sel.sum() >= 30:
                    split[key][f"{lo:g}-{hi:g}"] = row(sel)
        out[name] = split
    return out


def main() -> None:
    """Command line: print the fitted model (and ``--json`` the whole result)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("recording", type=Path)
    ap.add_argument("scenario")
    ap.add_argument("--max-frames", type=int, default=None)
    ap.add_argument("--json", action="store_true")
    ap.add_argument("--anchor", action="store_true", help="KltParams.anchor_templates (drift correction)")
    ap.add_argument(
        "--projective-after-px",
        type=float,
        default=float("inf"),
        help="KltParams.anchor_projective_after_px (homography anchors; default inf: affine)",
    )
    ap.add_argument("--klt", action="append", default=[], help="other KltParams field=value (repeatable)")
    a = ap.parse_args()
    klt = {k: ast.literal_eval(v) for k, _, v in (item.partition("=") for item in a.klt)}
    errors, depth_step = track_errors(
        a.recording,
        a.scenario,
        a.max_frames,
        anchor=a.anchor,
        projective_after_px=a.projective_after_px,
        klt=klt,
    )
    res = fit_noise(errors)
    res["core"] = fit_core(errors)
    res["bias"] = bias_split(errors, depth_step)
    if a.json:
        print(json.dumps(res, indent=1))
        return
    for k, v in res.items():
        print(f"{k:40s} {v}")


if __name__ == "__main__":
    main()
