"""Feature front ends and the feature database (open_vins ``TrackKLT`` / ``TrackSIM`` / ``FeatureDatabase``).

Both front ends implement one small interface, ``process(frame, t_imu_s) -> Tracks``:

- :class:`KltTracker` works on images: FAST corners with grid bucketing, pyramidal Lucas-Kanade
  (``cv2.calcOpticalFlowPyrLK``) with a forward-backward check, and RANSAC on the fundamental matrix of the
  undistorted points (``cv2.findFundamentalMat``).
- :class:`SimFeatureTracker` is the fast mode: it takes the simulated projections ``frame.features``.

Observations leave the front end as undistorted normalized coordinates. :class:`FeatureDatabase` stores them
per clone time and camera in fixed arrays and answers time-based queries (:mod:`.feature_database`).
"""

from __future__ import annotations

from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Protocol

import cv2
import numpy as np
from viotb.vio.camera import PinholeCamera
from viotb.vio.feature_database import FeatureDatabase
from viotb.vio.klt_anchor import TemplateAnchors
from viotb.vio.klt_detect import detect_corners
from viotb.vio.klt_flow import LK_NO_ERROR_PASS
from viotb.vio.types import CameraFrame

__all__ = [
    "FeatureDatabase",
    "FrontEnd",
    "KltParams",
    "KltTracker",
    "SimFeatureTracker",
    "Tracks",
    "make_frontend",
]


@dataclass(frozen=True)
class Tracks:
    """Feature observations of one frame, in cam0 and (stereo rigs) cam1.

    The cam0 fields are what every consumer of a mono front end reads (keyframing, zero-velocity test,
    initialization); the cam1 fields are empty for a mono rig. A track id names one landmark in both
    cameras, so an observation is ``(id, camera index, xy)``: :meth:`camera` returns one camera's.

    Attributes:
        t_cam_s: Camera timestamp (s).
        t_imu_s: The same instant on the IMU clock (s).
        ids: Track ids seen in cam0, shape (M,), int64.
        xy_norm: Undistorted normalized coordinates in cam0, shape (M, 2).
        uv_px: Measured (distorted) cam0 pixels, shape (M, 2).
        ids_right: Track ids seen in cam1, shape (M1,), int64.
        xy_norm_right: Undistorted normalized coordinates in cam1 (its own intrinsics), shape (M1, 2).
        uv_px_right: Measured (distorted) cam1 pixels, shape (M1, 2).
    """

    t_cam_s: float
    t_imu_s: float
    ids: np.ndarray
    xy_norm: np.ndarray
    uv_px: np.ndarray
    ids_right: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    xy_norm_right: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))
    uv_px_right: np.ndarray = field(default_factory=lambda: np.zeros((0, 2)))

    def __len__(self) -> int:
        """Number of cam0 observations."""
        return int(self.ids.shape[0])

    @property
    def num_cameras(self) -> int:
        """2 when this frame has cam1 observations, else 1."""
        return 2 if len(self.ids_right) else 1

    def camera(self, cam: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Observations of camera ``cam`` (0 or 1): ``(ids (M,), xy_norm (M, 2), uv_px (M, 2))``."""
        if cam == 0:
            return self.ids, self.xy_norm, self.uv_px
        if cam == 1:
            return self.ids_right, self.xy_norm_right, self.uv_px_right
        raise ValueError(f"Tracks.camera: camera index must be 0 or 1, got {cam}")

    @staticmethod
    def empty(t_cam_s: float, t_imu_s: float) -> Tracks:
        """A frame without observations."""
        return Tracks(t_cam_s, t_imu_s, np.zeros(0, dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2)))


class FrontEnd(Protocol):
    """What the MSCKF needs from a front end."""

    def process(self, frame: CameraFrame, t_imu_s: float) -> Tracks:
        """Track features in ``frame`` and return this frame's observations."""


@dataclass(frozen=True)
class KltParams:
    """KLT tracker settings (sizes for 320x240; scale with the image).

    Attributes:
        max_features: Target number of tracked features.
        grid_cols: Bucketing grid columns.
        grid_rows: Bucketing grid rows.
        fast_threshold: FAST intensity threshold (gray levels).
        min_distance_px: Minimum distance (px) between a new corner and any tracked feature.
        win_size_px: Lucas-Kanade window side (px).
        pyramid_levels: Extra pyramid levels.
        fb_max_error_px: Largest forward-backward error (px).
        fb_win_size_px: Lucas-Kanade window side (px) of the backward (check) pass.
        fb_epsilon_px: Convergence threshold (px) of the backward pass's iterations (the forward pass uses
            OpenCV's default of 0.01 px with at most 30 iterations).
        fb_max_level: Pyramid levels of the backward pass when it starts at each point's previous position
            (VINS-Fusion's ``FLOW_BACK``: level 1, initial flow at the previous points; Qin, Li, Shen,
            TRO 2018); None (default): a full search from the tracked position (``pyramid_levels``, no
            initial flow, the Kalal-Mikolajczyk-Matas forward-backward error). Level 1 saves 1-1.5 ms of
            CPU per 320x240 frame and keeps more tracks (look-around: 2376 against 2662 track starts in 300
            frames), but the MSCKF's ATE rose on 5 of 8 recordings (headset look-around stereo 20 s seed 0
            5.99 -> 6.17 mm, 8 s seed 1 6.18 -> 6.53, seed 2 7.19 -> 7.07; mono 6.31 -> 6.75 and 7.17 -> 7.38;
            aggressive 14.0 -> 14.4 mm, NEES 2.0 -> 2.4; figure8 seeds 0-2 identical; 752x480 11.4 -> 9.9),
            so the default stays the full search.
        ransac_threshold_px: RANSAC epipolar threshold (px, on undistorted points scaled by the focal length).
        ransac_confidence: RANSAC confidence.
        border_px: Features closer than this to the border (px) are dropped.
        track_random_walk_px2_per_px: Variance (px^2) that a track's error gains per pixel the feature moves
            in the image (the tracked point slides over the texture: a random walk clocked by image motion),
            for the MSCKF's measurement model; 0 = white noise only. ``benchmarks/klt_track_error.py``
            measures it against the exact projection of each track's first 3-D point on rendered
            recordings (320x240): frame to frame, 0.015-0.03 px^2/px on ``figure8`` and ``aggressive``; with
            the affine anchoring below 0.0027 on ``figure8`` (12 s, seed 0). The default, 0.005, is that
            measurement with a factor 2 of margin, for real images (unmeasured). On the renders the tracks
            walk 0.00003-0.0004 px^2/px (robust and non-robust fits, 20 s recordings):
            :data:`viotb.vio.msckf_params.RENDER_KLT_TRACK_RANDOM_WALK_PX2_PER_PX`.
        anchor_templates: Refine every frame-to-frame position by aligning the track's first-frame template
            with an affine warp (drift correction, :mod:`viotb.vio.klt_anchor`); a refinement that fails
            takes the template anew. Measured (README "KLT track error"): the error of a track 120-400 px
            from where it started 1.38 -> 0.35 px RMS on the stereo look-around; MSCKF ATE on 12 s
            ``figure8`` / ``aggressive`` / ``circle`` 3.2 / 2.3 / 2.5 -> 1.8 / 1.4 / 1.0 cm; costs ~3.4 ms of
            CPU per 320x240 frame.
        anchor_half_size_px: Half side (px) of the anchor templates.
        anchor_max_shift_px: Largest accepted refinement (px) away from the frame-to-frame position.
        anchor_min_zncc: Smallest accepted normalized cross-correlation of an aligned template.
        anchor_projective_after_px: A track at least this far (px) from where its template was taken is
            aligned with a homography instead of an affine warp (``TemplateAnchors.projective_after_px``;
            ``inf``: affine only, the behaviour before). An affine anchor on a foreshortened plane drifts
            one way (``circle`` seed 0, floor tracks: +0.036 / +0.080 / +0.19 px in v after 30-60 / 60-120 /
            120-400 px; with these defaults +0.008 / +0.006 / +0.000; README "KLT track bias on
            foreshortened planes"). 20 px, not 10: from 10 px the drone recordings do slightly better but the
            headset look-around worse (seed 0 world lock 4.9 -> 6.4 mm; 5.4 from 20 px).
        anchor_iterations: Gauss-Newton iterations of the anchor alignment per frame (the warp is carried
            from frame to frame, so 2 reach the accuracy of 4: ``circle`` seed 0 robust white sigma 0.033
            against 0.035 px; 4 was the default before, and the homography with 4 cost 17 % more KLT CPU).
        anchor_fail_ends_track: A track whose anchoring fails ends there and a new track starts at its
            position with a new template (False, the behaviour before: the track goes on, its template
            taken anew at the drifted position, so its error walks on under one id).
        fb_check_anchored: Track back (the forward-backward check) every track, then anchor the kept ones
            (True, the default). False: the forward result is anchored first, and a track whose anchoring
            is accepted within ``fb_unchecked_shift_px`` of it is not tracked back (the anchoring's tests,
            ZNCC against the track's first template, shift and stretch, stand in for the check); the
            others are (no template yet, refused, or moved further by the anchoring). It saves most of a
            KLT pass (stereo look-around, front end 14.3 -> 11.3 ms CPU per frame with the two options
            below, 12.9 without this one; mono ``figure8`` 11.7 -> 8.9 ms), but the look-around's world
            lock did not hold: 4.96 / 3.82 / 2.40 mm on seeds 0 / 1 / 2 became 4.53 / 4.85 / 4.26 mm (max
            7.8 / 8.5 / 9.2 mm, NEES 3.3 / 5.1 / 3.3; README "MSCKF per frame"), so it is off.
        fb_unchecked_shift_px: See ``fb_check_anchored``. On the stereo look-around (cam0, 20 s, seed 0)
            87 % of the anchored tracks stay within 0.25 px. Tracking none of the anchored tracks back
            (``inf``) let a few gross errors through (track error against the truth, RMS over 106k
            observations: 0.139 px checked, 0.21-0.26 px unchecked, the median 0.064 px either way;
            world lock 5.32 / 3.99 / 2.49 mm on seeds 0-2).
        anchor_zncc_at_final_warp: ``TemplateAnchors.zncc_at_final_warp`` (True, the default: one more
            remap of all patches per frame).
        anchor_compiled: ``TemplateAnchors.compiled``: the alignment (README "MSCKF per frame", session
            10) and the template taking (session 13: front end wall median 4.19 -> 3.76 ms on ``figure8``,
            5.20 -> 4.64 ms on ``head-fast-turns``) in compiled kernels (True, the default) or in numpy (the
            reference).
        parallel_anchoring: With ``fb_check_anchored`` and ``anchor_compiled``: anchor every track the
            forward pass kept in a second thread during the backward pass (both release the GIL), then keep
            those the check kept: the kernel aligns each track on its own and a dropped track ends, so the
            tracks are the sequential ones. Saves wall time, not CPU.
        lk_skip_error_pass: Run the Lucas-Kanade passes without OpenCV's final error pass
            (:data:`viotb.vio.klt_flow.LK_NO_ERROR_PASS`; the tracker never reads the error). The same
            tracks bit for bit: the pass only changes the status of points that ended beyond the image's
            window padding, which the border and forward-backward tests refuse anyway. ~5 % of the KLT.
        parallel_detection: Run the FAST detection of the new image in the worker thread during the forward
            pass (it needs only the image; the tracked points filter its corners afterwards).
        deferred_templates: With ``anchor_compiled``: run the new tracks' template kernel in the worker
            thread after the frame is returned (the next frame's anchoring, which first reads them, stores
            them), so it runs beside the estimator's update. Both give the same tracks bit for bit (README
            "MSCKF per frame").
    """

    max_features: int = 180
    grid_cols: int = 8
    grid_rows: int = 6
    fast_threshold: int = 15
    min_distance_px: float = 10.0
    win_size_px: int = 15
    pyramid_levels: int = 3
    fb_max_error_px: float = 1.0
    fb_win_size_px: int = 15
    fb_epsilon_px: float = 0.01
    fb_max_level: int | None = None
    ransac_threshold_px: float = 1.0
    ransac_confidence: float = 0.99
    border_px: float = 3.0
    track_random_walk_px2_per_px: float = 0.005
    anchor_templates: bool = True
    anchor_half_size_px: int = 5
    anchor_max_shift_px: float = 2.0
    anchor_min_zncc: float = 0.85
    anchor_projective_after_px: float = 20.0
    anchor_iterations: int = 2
    anchor_fail_ends_track: bool = True
    fb_check_anchored: bool = True
    fb_unchecked_shift_px: float = 0.25
    anchor_zncc_at_final_warp: bool = True
    anchor_compiled: bool = True
    parallel_anchoring: bool = True
    lk_skip_error_pass: bool = True
    parallel_detection: bool = True
    deferred_templates: bool = True


class KltTracker:
    """Image front end: FAST + grid bucketing, pyramidal KLT with forward-backward check, F-matrix RANSAC.

    Args:
        camera: Intrinsics (image size and distortion).
        params: Settings.
    """

    def __init__(self, camera: PinholeCamera, params: KltParams | None = None) -> None:
        """Create a tracker with no history."""
        self.camera = camera
        self.params = params if params is not None else KltParams()
        self._fast = cv2.FastFeatureDetector_create(
            threshold=self.params.fast_threshold, nonmaxSuppression=True
        )
        self._prev_img: np.ndarray | None = None
        self._prev_pts = np.zeros((0, 2), dtype=np.float32)
        self._prev_ids = np.zeros(0, dtype=np.int64)
        self._prev_xy = np.zeros((0, 2))  # undistorted normalized coordinates of ``_prev_pts``
        self._next_id = 0
        self._focal_px = 0.5 * (camera.fx + camera.fy)
        self._dist = np.array(camera.distortion, dtype=float)
        self._undistort_criteria = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, 1e-12)
        self._anchors = self._new_anchors()
        self._executor: ThreadPoolExecutor | None = None
        self._templates: Future | None = None  # the deferred template taking of the previous frame
        self._corners: Future | None = None  # the FAST corners of the frame being tracked

    def _new_anchors(self) -> TemplateAnchors | None:
        p = self.params
        if not p.anchor_templates:
            return None
        return TemplateAnchors(
            p.anchor_half_size_px,
            max_shift_px=p.anchor_max_shift_px,
            min_zncc=p.anchor_min_zncc,
            projective_after_px=p.anchor_projective_after_px,
            iterations=p.anchor_iterations,
            zncc_at_final_warp=p.anchor_zncc_at_final_warp,
            compiled=p.anchor_compiled,
        )

    def undistort(self, uv_px: np.ndarray) -> np.ndarray:
        """Pixels (N, 2) -> undistorted normalized coordinates (N, 2).

        Radial-tangential cameras use OpenCV's iterative inverse (``cv2.undistortPoints``); other models
        (equidistant) their own ``undistort_points``.
        """
        uv = np.asarray(uv_px, dtype=float).reshape(-1, 2)
        if self.camera.distortion_model != "radial-tangential":
            return self.camera.undistort_points(uv) if len(uv) else np.zeros((0, 2))
        if not self.camera.has_distortion or len(uv) == 0:
            return self.camera.undistort_points(uv) if len(uv) else np.zeros((0, 2))
        out = cv2.undistortPoints(
            uv.reshape(-1, 1, 2),
            self.camera.K,
            self._dist,
            R=np.eye(3),
            P=np.eye(3),
            criteria=self._undistort_criteria,
        )
        return out.reshape(-1, 2)

    def _check_image(self, image: np.ndarray) -> np.ndarray:
        img = np.asarray(image)
        if img.ndim == 3 and img.shape[2] == 3:
            img = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)
        expected = (self.camera.height, self.camera.width)
        if img.ndim != 2 or img.shape != expected:
            raise ValueError(
                f"KltTracker: image shape {img.shape} does not match the camera ({expected[0]}x{expected[1]} "
                "rows x cols, grayscale)"
            )
        if img.dtype != np.uint8:
            raise ValueError(f"KltTracker: image dtype must be uint8, got {img.dtype}")
        return img

    def reset(self) -> None:
        """Forget the previous frame (all tracks end)."""
        self._join_templates()
        self._prev_img = None
        self._prev_pts = np.zeros((0, 2), dtype=np.float32)
        self._prev_ids = np.zeros(0, dtype=np.int64)
        self._prev_xy = np.zeros((0, 2))
        self._anchors = self._new_anchors()

    def _track(
        self, img: np.ndarray, img_f32: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """KLT from the previous frame, template anchoring, forward-backward check and RANSAC.

        The backward pass checks the tracks that have no accepted anchoring (all of them with
        ``fb_check_anchored``, which anchors after the check, as before).

        Args:
            img: The new image (uint8).
            img_f32: The same image as float32, for the anchoring (None without anchors).

        Returns:
            ``(pts (M, 2) float32 px, ids (M,), xy (M, 2) undistorted normalized, fresh (M,) bool)``;
            ``fresh`` marks the tracks whose anchoring failed (their template is to be taken anew).
            Undistortion is per point, so the previous frame's coordinates are reused and each point is
            undistorted once.
        """
        p = self.params
        if self._prev_img is None or len(self._prev_pts) == 0:
            empty = np.zeros(0, dtype=np.int64)
            return np.zeros((0, 2), dtype=np.float32), empty, np.zeros((0, 2)), empty.astype(bool)
        flags = LK_NO_ERROR_PASS if p.lk_skip_error_pass else 0
        lk = {"winSize": (p.win_size_px, p.win_size_px), "maxLevel": p.pyramid_levels, "flags": flags}
        p0 = self._prev_pts.reshape(-1, 1, 2)
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(self._prev_img, img, p0, None, **lk)
        p1 = p1.reshape(-1, 2)
        good = (st1.ravel() == 1) & self.camera.in_image(p1.astype(float), p.border_px)
        anchored = np.zeros(len(p1), dtype=bool)
        unchecked = np.zeros(len(p1), dtype=bool)  # anchored close to the forward result: not tracked back
        if self._anchors is not None and not p.fb_check_anchored:
            # The anchoring checks the tracks that have a template (ZNCC against the first template, the
            # shift from the forward result): only the others are tracked back.
            fwd = np.flatnonzero(good)
            if len(fwd):
                refined, ok = self._anchors.refine(img_f32, self._prev_ids[fwd], p1[fwd])
                unchecked[fwd] = ok & (np.linalg.norm(refined - p1[fwd], axis=1) <= p.fb_unchecked_shift_px)
                p1[fwd] = refined.astype(np.float32)
                anchored[fwd] = ok
        # Backward pass only for the points the forward pass kept (LK tracks each point on its own).
        fwd = np.flatnonzero(good & ~unchecked)
        ahead = None  # the anchoring of every forward-kept track, running beside the backward pass
        if p.fb_check_anchored and p.parallel_anchoring and p.anchor_compiled and len(fwd):
            if self._anchors is not None:
                ahead = self._pool().submit(self._anchors.refine, img_f32, self._prev_ids[fwd], p1[fwd])
        if len(fwd):
            back = {
                "winSize": (p.fb_win_size_px, p.fb_win_size_px),
                "maxLevel": p.pyramid_levels if p.fb_max_level is None else p.fb_max_level,
                "criteria": (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 30, p.fb_epsilon_px),
                "flags": flags,
            }
            p1_fwd = p1[fwd].reshape(-1, 1, 2)
            start = None
            if p.fb_max_level is not None:
                start = self._prev_pts[fwd].reshape(-1, 1, 2).copy()
                back["flags"] = flags | cv2.OPTFLOW_USE_INITIAL_FLOW
            p0r, st2, _ = cv2.calcOpticalFlowPyrLK(img, self._prev_img, p1_fwd, start, **back)
            fb = np.linalg.norm(p0r.reshape(-1, 2) - self._prev_pts[fwd], axis=1)
            good[fwd] = (st2.ravel() == 1) & (fb < p.fb_max_error_px)
        pts, ids, xy_prev = p1[good], self._prev_ids[good], self._prev_xy[good]
        fresh = np.zeros(len(pts), dtype=bool) if self._anchors is None else ~anchored[good]
        if ahead is not None:
            refined, ok = ahead.result()
            kept = good[fwd]
            pts, fresh = refined[kept].astype(np.float32), ~ok[kept]
        elif self._anchors is not None and p.fb_check_anchored and len(pts):
            refined, ok = self._anchors.refine(img_f32, ids, pts)
            pts, fresh = refined.astype(np.float32), ~ok
        xy = self.undistort(pts)
        if len(pts) >= 8:
            a = xy_prev * self._focal_px
            b = xy * self._focal_px
            _, inl = cv2.findFundamentalMat(a, b, cv2.FM_RANSAC, p.ransac_threshold_px, p.ransac_confidence)
            if inl is not None:
                keep = inl.ravel().astype(bool)
                pts, ids, xy, fresh = pts[keep], ids[keep], xy[keep], fresh[keep]
        return pts, ids, xy, fresh

    def _pool(self) -> ThreadPoolExecutor:
        """The tracker's one worker thread (created on first use)."""
        if self._executor is None:
            self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="klt-anchor")
        return self._executor

    def _join_templates(self) -> None:
        """Store the previous frame's templates once taken (``deferred_templates``; re-raises its error)."""
        if self._templates is not None:
            (job, computing), self._templates = self._templates, None
            self._anchors.end_take(job, computing.result())

    def _detect(self, img: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """New FAST corners, bucketed on a grid and away from tracked points, shape (N, 2) float32."""
        job, self._corners = self._corners, None
        kps = None if job is None else job.result()
        return detect_corners(self._fast, self.camera, self.params, img, pts, kps)

    def process(self, frame: CameraFrame, t_imu_s: float) -> Tracks:
        """Track into ``frame.image``; an absent/empty or featureless image yields zero tracks.

        Args:
            frame: The camera frame.
            t_imu_s: Its time on the IMU clock (s).

        Raises:
            ValueError: if the image size or type does not match the camera.
        """
        if frame.image is None or np.asarray(frame.image).size == 0:
            self.reset()
            return Tracks.empty(frame.t_s, t_imu_s)
        img = self._check_image(frame.image)
        self._join_templates()
        p = self.params
        # FAST beside the forward pass (it needs only the image; ``_detect`` filters its corners).
        self._corners = self._pool().submit(self._fast.detect, img, None) if p.parallel_detection else None
        img_f32 = img.astype(np.float32) if self._anchors is not None else None
        pts, ids, xy, fresh = self._track(img, img_f32)
        if self.params.anchor_fail_ends_track and np.any(fresh):
            # A failed anchoring would take the template anew at the drifted position: the track ends
            # there and a new one starts (the filter does not take the two for one point).
            n_fresh = int(fresh.sum())
            ids = ids.copy()
            ids[fresh] = np.arange(self._next_id, self._next_id + n_fresh, dtype=np.int64)
            self._next_id += n_fresh
        new = self._detect(img, pts)
        if len(new):
            new_ids = np.arange(self._next_id, self._next_id + len(new), dtype=np.int64)
            self._next_id += len(new)
            pts = np.vstack([pts, new]).astype(np.float32)
            ids = np.concatenate([ids, new_ids])
            xy = np.vstack([xy, self.undistort(new)])
            fresh = np.concatenate([fresh, np.ones(len(new), dtype=bool)])
        if self._anchors is not None:
            # The ended tracks' templates go; the new tracks' and failed anchorings' are taken in one batch,
            # with ``deferred_templates`` by the worker (only the kernel, which releases the GIL: Python
            # there would hold up the estimator's update in this thread by the switch interval).
            self._anchors.keep_only(ids)
            job = self._anchors.begin_take(img_f32, ids[fresh], pts[fresh])
            if job is not None and p.deferred_templates and p.anchor_compiled:
                self._templates = (job, self._pool().submit(job.compute))
            elif job is not None:
                self._anchors.end_take(job, job.compute())
        self._prev_img, self._prev_pts, self._prev_ids = img, pts.astype(np.float32), ids
        self._prev_xy = xy
        return Tracks(frame.t_s, t_imu_s, ids, xy, pts.astype(float))


class SimFeatureTracker:
    """Fast mode: uses the simulated projections in ``frame.features`` (no image processing).

    Args:
        camera: Intrinsics used to undistort the pixels.
    """

    def __init__(self, camera: PinholeCamera) -> None:
        """Create the tracker."""
        self.camera = camera

    def process(self, frame: CameraFrame, t_imu_s: float) -> Tracks:
        """Observations of ``frame.features`` (zero tracks when it is None or empty)."""
        obs = frame.features
        if obs is None or len(obs.ids) == 0:
            return Tracks.empty(frame.t_s, t_imu_s)
        uv = np.asarray(obs.uv_px, dtype=float).reshape(-1, 2)
        ids = np.asarray(obs.ids, dtype=np.int64).ravel()
        if len(ids) != len(uv):
            raise ValueError(f"SimFeatureTracker: {len(ids)} ids but {len(uv)} uv_px rows")
        ok = np.all(np.isfinite(uv), axis=1)
        return Tracks(frame.t_s, t_imu_s, ids[ok], self.camera.undistort_points(uv[ok]), uv[ok])


def make_frontend(kind: str, camera: PinholeCamera, klt: KltParams, owner: str) -> FrontEnd:
    """The front end named ``kind``: ``"klt"`` (images) or ``"sim"`` (``frame.features``).

    Args:
        kind: Front-end name.
        camera: Intrinsics.
        klt: KLT settings (used by ``"klt"``).
        owner: Settings class named in the error (e.g. ``"MsckfParams"``).

    Raises:
        ValueError: Unknown ``kind``, naming ``owner.frontend`` and the value.
    """
    if kind == "klt":
        return KltTracker(camera, klt)
    if kind == "sim":
        return SimFeatureTracker(camera)
    raise ValueError(f"{owner}.frontend must be 'klt' or 'sim', got {kind!r}")
