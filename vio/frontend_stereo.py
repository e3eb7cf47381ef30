"""Stereo front end: mono tracking on cam0 plus left-right correspondences in cam1 (open_vins ``TrackKLT``).

:class:`StereoTracker` wraps a mono front end (:class:`~viotb.vio.frontend.KltTracker` or
:class:`~viotb.vio.frontend.SimFeatureTracker`) that tracks cam0 over time, and adds each frame's cam1
observations of the same track ids:

- images (``frame.image_right``): every tracked cam0 point is matched into cam1 with
  :func:`viotb.vio.stereo.match_stereo` (KLT left -> right from a guess at the track's previous stereo depth,
  KLT right -> left as a reverse check, an epipolar check from the known extrinsics, and a depth range).
  open_vins tracks cam1 over time on its own and matches left-right only at detection; here the right
  observation is found again from the left one every frame, so a cam1 observation is always consistent with
  cam0 (no right-only tracks) at the cost of one left-right KLT per frame.
- simulated features (``frame.features_right``): the simulated cam1 projections, undistorted with cam1's
  intrinsics (ids seen only in cam1 are kept).

A frame without right data yields the mono tracks unchanged.
"""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.frontend import FrontEnd, Tracks
from viotb.vio.stereo import StereoMatchParams, match_stereo
from viotb.vio.types import CameraFrame


def _gray(image: np.ndarray, expected_hw: tuple[int, int], which: str) -> np.ndarray:
    """Grayscale uint8 image of the expected (rows, cols); RGB is converted (ValueError otherwise)."""
    img = np.asarray(image)
    if img.ndim == 3 and img.shape[2] == 3:
        img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
    if img.ndim != 2 or img.shape != expected_hw or img.dtype != np.uint8:
        raise ValueError(
            f"StereoTracker: {which} image shape {img.shape} dtype {img.dtype} does not match the camera "
            f"({expected_hw[0]}x{expected_hw[1]} rows x cols, grayscale uint8)"
        )
    return img


class StereoTracker:
    """Cam0 tracking over time (the wrapped front end) plus cam1 observations of the same tracks.

    Args:
        mono: Front end tracking cam0 over time.
        calib0: Cam0 calibration (intrinsics and ``R_BC``, ``p_BC``).
        calib1: Cam1 calibration.
        params: Left-right matching settings.
    """

    def __init__(
        self,
        mono: FrontEnd,
        calib0: CameraCalibration,
        calib1: CameraCalibration,
        params: StereoMatchParams | None = None,
    ) -> None:
        """Create the tracker with no depth history."""
        self.mono = mono
        self.calib0 = calib0
        self.calib1 = calib1
        self.params = params if params is not None else StereoMatchParams()
        # The tracks matched in the previous frame (ids sorted) and their stereo depths (m).
        self._prior_ids = np.zeros(0, dtype=np.int64)
        self._prior_depth_m = np.zeros(0)

    def process(self, frame: CameraFrame, t_imu_s: float) -> Tracks:
        """Track cam0 with the wrapped front end, then add this frame's cam1 observations.

        Raises:
            ValueError: if an image does not match its camera.
        """
        images = frame.image_right is not None and frame.image is not None and np.asarray(frame.image).size
        tracks = self.mono.process(frame, t_imu_s)
        if images:
            return self._match_images(frame, tracks)
        if frame.features_right is not None:
            return self._sim_right(frame, tracks)
        return tracks

    def _prior(self, ids: np.ndarray) -> np.ndarray:
        """Last frame's stereo depth (m) of each track id (NaN where it had none), shape (M,)."""
        prior = np.full(len(ids), np.nan)
        if len(self._prior_ids):
            pos = np.minimum(np.searchsorted(self._prior_ids, ids), len(self._prior_ids) - 1)
            hit = self._prior_ids[pos] == ids
            prior[hit] = self._prior_depth_m[pos[hit]]
        return prior

    def _match_images(self, frame: CameraFrame, tracks: Tracks) -> Tracks:
        cam0, cam1 = self.calib0.camera, self.calib1.camera
        if len(tracks) == 0:
            self._prior_ids, self._prior_depth_m = np.zeros(0, dtype=np.int64), np.zeros(0)
            return tracks
        img0 = _gray(frame.image, (cam0.height, cam0.width), "left")
        img1 = _gray(frame.image_right, (cam1.height, cam1.width), "right")
        ids = tracks.ids
        prior = self._prior(ids)
        m = match_stereo(img0, img1, tracks.uv_px, self.calib0, self.calib1, self.params, prior)
        order = np.argsort(ids[m.mask], kind="stable")
        self._prior_ids, self._prior_depth_m = ids[m.mask][order], m.depth_m[m.mask][order]
        uv1 = m.uv1_px[m.mask]
        xy1 = cam1.undistort_points(uv1) if len(uv1) else np.zeros((0, 2))
        return replace(tracks, ids_right=ids[m.mask].copy(), xy_norm_right=xy1, uv_px_right=uv1)

    def _sim_right(self, frame: CameraFrame, tracks: Tracks) -> Tracks:
        obs = frame.features_right
        assert obs is not None
        uv = np.asarray(obs.uv_px, dtype=float).reshape(-1, 2)
        ids = np.asarray(obs.ids, dtype=np.int64).ravel()
        if len(ids) != len(uv):
            raise ValueError(f"StereoTracker: {len(ids)} right ids but {len(uv)} right uv_px rows")
        ok = np.all(np.isfinite(uv), axis=1)
        if not np.any(ok):
            return tracks
        uv, ids = uv[ok], ids[ok]
        xy = self.calib1.camera.undistort_points(uv)
        return replace(tracks, ids_right=ids, xy_norm_right=xy, uv_px_right=uv)


def make_stereo_frontend(
    mono: FrontEnd,
    calib0: CameraCalibration,
    calib1: CameraCalibration | None,
    params: StereoMatchParams | None = None,
) -> FrontEnd:
    """``mono`` itself for a mono rig (``calib1`` None), else a :class:`StereoTracker` around it."""
    if calib1 is None:
        return mono
    return StereoTracker(mono, calib0, calib1, params)
