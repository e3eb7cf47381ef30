"""The loop-closure facade: one call per camera frame, decoupled from the estimator.

Per frame: ``add_frame(t, image, R_WB, p_WB, calib)`` with the estimator's pose in its own odometry frame.
Keyframes (every 0.3 m or 15 deg) get ORB features and landmarks triangulated against the previous keyframes;
each new keyframe queries the bag-of-words database (keyframes of its own sequence only when
``min_time_gap_s`` older; other localized sequences and a loaded map all), verifies the best candidates with
PnP RANSAC, checks the first verified one against the odometry's drift bound and holds it until the next
keyframe confirms it (:mod:`viotb.vio.loop.consistency`); then both loop edges go into the 4-DOF pose graph
and it is solved. The result is published as ``T_W_corrected_from_W_odom`` (blended in over
``blend_duration_s``), so the estimator's state is never touched: ``corrected_pose(t, R_WB, p_WB)`` maps any
odometry pose to the map; ``smoothed_corrections`` gives the whole run's final (non-causal) corrections.

Sequences and relocalization (VINS-Mono's ``sequence``): a tracking loss (``notify_tracking_lost()``, or a
frame gap over ``tracking_loss_gap_s``) starts a new odometry sequence that is not localized: its keyframes
stay out of the graph and the correction in force is kept (an estimator that coasts through a blackout keeps
its frame) until two keyframes are verified against localized ones and agree; then ``T_map_odom`` of the
sequence is the 4-DOF transform that puts the query where PnP says, the sequence joins the graph and the
graph is solved. A run started with ``load_map`` is such a sequence: it localizes into the map's frame at its
first recognized place (snapping, since its odometry frame was arbitrary), with the map's keyframes fixed.
After a tracking loss, keyframes come every ``relocalization_keyframe_interval_s`` whatever the motion, until
the sequence relocalizes and for ``relocalization_dense_s`` after: a hovering drone that lost its features
(lights out) gets its query keyframe and its confirmation within half a second of the light returning, and
the closures that follow correct the drift of its re-initialized filter while it converges.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from viotb.vio.camera import CameraCalibration
from viotb.vio.lie import rotz
from viotb.vio.loop.bow import BowDatabase, shipped_vocabulary, train_vocabulary
from viotb.vio.loop.consistency import Candidate, ConsistencyGate, make_candidate
from viotb.vio.loop.correction import CorrectionBlender
from viotb.vio.loop.frames import (
    RigidTransform,
    drift_4dof,
    heading_rad,
    horizontal_axis_B,
    interpolate,
    loop_4dof,
    relative_4dof,
)
from viotb.vio.loop.keyframes import Keyframe, KeyframeDatabase
from viotb.vio.loop.map_io import read_map_arrays, write_map_arrays
from viotb.vio.loop.params import LoopClosureParams
from viotb.vio.loop.pose_graph import Edge4Dof, PoseGraph4Dof, SolveReport
from viotb.vio.loop.records import FrameTiming, LoopClosure
from viotb.vio.loop.serialize import keyframes_from_arrays, map_arrays
from viotb.vio.loop.verification import verify_candidate


class LoopCloser:
    """Keyframes, place recognition, verification, pose graph and drift correction behind one call per frame.

    Args:
        params: All parameters.
        vocabulary: Bag-of-words vocabulary, shape (W, 32) uint8; None takes the shipped one
            (``recognition.shipped_vocabulary``) or trains one from the first keyframes.
    """

    def __init__(self, params: LoopClosureParams | None = None, vocabulary: np.ndarray | None = None) -> None:
        """A fresh closer: sequence 0 is the map frame, no keyframes."""
        self.params = params or LoopClosureParams()
        self.db = KeyframeDatabase(self.params.keyframes)
        self.graph = PoseGraph4Dof(self.params.pose_graph)
        self.blender = CorrectionBlender(self.params.blend_duration_s)
        if vocabulary is None and self.params.recognition.shipped_vocabulary:
            vocabulary = shipped_vocabulary()
        self.bow: BowDatabase | None = None if vocabulary is None else BowDatabase(vocabulary)
        self.gate = ConsistencyGate(self.params.consistency)
        self.last_solve: SolveReport | None = None
        self._path_m = 0.0  # odometry path length over keyframes of the current sequence (m)
        self._path_at_anchor_m = 0.0  # ... at its last accepted closure (or its start)
        self.closures: list[LoopClosure] = []
        self.timings: list[FrameTiming] = []
        self.sequence = 0
        self._localized: set[int] = {0}
        self._map_edges: list[Edge4Dof] = []
        self._last_t_s: float | None = None
        self._lost = False
        self._first_own_sequence = 0  # sequences below are a loaded map's
        self._loaded_map = False
        self._n_loaded_closures = 0
        self.heading_axis_B: np.ndarray | None = None  # set at the first keyframe or by load_map
        self.verified_corrections: list[tuple[float, int, int, np.ndarray, RigidTransform]] = []
        """Per verified loop in order (before the drift bound and the confirmation): query time (s), its
        sequence, the match keyframe's index, the query's odometry position (m, (3,)) and the 4-DOF
        ``T_map_odom`` the loop alone implies
        (``Candidate.correction``): how the drift of a sequence changes between its loops
        (``FlightLoopClosure.drift_velocity``)."""
        self._dense_sequence: int | None = None  # the sequence started by the latest tracking loss
        self._dense_until_s = np.inf  # its dense keyframes end then (set at its relocalization)

    def _yaw(self, R_WB: np.ndarray) -> float:
        return heading_rad(R_WB, self.heading_axis_B)

    @property
    def run_closures(self) -> list[LoopClosure]:
        """The closures accepted in this run (``closures`` also holds a loaded map's)."""
        return self.closures[self._n_loaded_closures :]

    @property
    def localized(self) -> bool:
        """Whether the current odometry sequence is tied to the map frame."""
        return self.sequence in self._localized

    def notify_tracking_lost(self) -> None:
        """The estimator lost track (and will restart in a new odometry frame): start a new sequence."""
        self._lost = True

    def notify_odometry_reset(
        self, R_WB_before: np.ndarray, p_WB_before: np.ndarray, R_WB_after: np.ndarray, p_WB_after: np.ndarray
    ) -> None:
        """The odometry jumped (an update moved the pose, another estimator took over): a new segment.

        The correction in force is carried over to the new odometry frame (``CorrectionBlender.reexpress``:
        the corrected pose does not jump), and the next frame starts a new sequence, as after a tracking
        loss: the keyframes before the jump keep their own odometry frame and edges (an odometry edge across
        the jump would read it as motion), and the new segment's first relocalization measures its
        ``T_map_odom`` afresh instead of checking its loops against a correction that was measured on the
        poses before the jump.

        Args:
            R_WB_before: The odometry attitude just before the jump, shape (3, 3).
            p_WB_before: The odometry position just before (m), shape (3,).
            R_WB_after: The same instant's attitude after the jump, shape (3, 3).
            p_WB_after: Its position after (m), shape (3,).
        """
        axis = self.heading_axis_B if self.heading_axis_B is not None else horizontal_axis_B(R_WB_before)
        self.blender.reexpress(drift_4dof(R_WB_after, p_WB_after, R_WB_before, p_WB_before, axis))
        self._lost = True

    def correction(self, t_s: float) -> RigidTransform:
        """``T_W_corrected_from_W_odom`` in force at ``t_s``, blended."""
        return self.blender.value(t_s)

    def corrected_pose(self, t_s: float, R_WB: np.ndarray, p_WB: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """An odometry pose ``(R_WB (3, 3), p_WB (3,) m)`` in the corrected (map) frame."""
        return self.correction(t_s).apply_pose(np.asarray(R_WB), np.asarray(p_WB))

    def add_frame(
        self,
        t_s: float,
        image_u8: np.ndarray,
        R_WB: np.ndarray,
        p_WB: np.ndarray,
        calib: CameraCalibration,
        points_W: np.ndarray | None = None,
        points_uv_px: np.ndarray | None = None,
        force_keyframe: bool = False,
    ) -> LoopClosure | None:
        """Process one camera frame with the estimator's pose.

        Args:
            t_s: Frame time (s).
            image_u8: Grayscale image, shape (H, W) uint8 (distorted, as the camera gives it).
            R_WB: Estimated attitude in the estimator's odometry frame, shape (3, 3).
            p_WB: Estimated position (m), shape (3,).
            calib: Camera calibration (intrinsics, distortion, ``R_BC``, ``p_BC``).
            points_W: Optional landmarks from the estimator (odometry frame, m), shape (M, 3).
            points_uv_px: Their pixels in this image, shape (M, 2).
            force_keyframe: Make the frame a keyframe whatever its motion: the last frame of a recording,
                so that the end of the final trajectory is tied to the pose graph (a run that ends back at
                its start slows down there, and its last keyframe by the motion rule may be a second old).

        Returns:
            The loop closure accepted at this frame, or None.
        """
        t0 = time.perf_counter()
        R_WB, p_WB = np.asarray(R_WB, dtype=float), np.asarray(p_WB, dtype=float)
        gap = self._last_t_s is not None and t_s - self._last_t_s > self.params.tracking_loss_gap_s
        if self._lost or gap:
            self._start_sequence(t_s)
        self._last_t_s = float(t_s)
        keyframe = force_keyframe or self.db.is_keyframe(t_s, R_WB, p_WB, self.sequence)
        if not (keyframe or self._dense_keyframe(t_s)):
            self.timings.append(FrameTiming(t_s, (time.perf_counter() - t0) * 1e3))
            return None
        if self.heading_axis_B is None:
            self.heading_axis_B = horizontal_axis_B(R_WB)
        uv, desc, landmarks_B, octaves = self.db.extract(image_u8, R_WB, p_WB, points_W, points_uv_px)
        kf = Keyframe(
            len(self.db),
            float(t_s),
            self.sequence,
            R_WB.copy(),
            p_WB.copy(),
            uv,
            desc,
            landmarks_B,
            octaves=octaves,
            landmark_sigma_m_per_px=np.where(np.isfinite(landmarks_B[:, 0]), 0.0, np.inf),
        )
        recent = self.db.recent_of_sequence(self.sequence, self.params.keyframes.triangulation_keyframes)
        for older in recent:
            self.db.triangulate(older, kf, calib)
        prev = recent[0] if recent else None
        if prev is not None:
            self._path_m += float(np.linalg.norm(kf.p_WB_odom - prev.p_WB_odom))
        t1 = time.perf_counter()
        candidates = self._candidates(kf)
        t2 = time.perf_counter()
        self._insert(kf, prev)
        accepted = self._verify(kf, candidates, calib)
        t3 = time.perf_counter()
        closure = self._close(accepted) if accepted else None
        t4 = time.perf_counter()
        self.timings.append(
            FrameTiming(
                t_s, (t4 - t0) * 1e3, True, (t1 - t0) * 1e3, (t2 - t1) * 1e3, (t3 - t2) * 1e3, (t4 - t3) * 1e3
            )
        )
        return closure

    def _dense_keyframe(self, t_s: float) -> bool:
        """Whether a frame is a keyframe by the dense rule after a tracking loss (module docstring)."""
        if self.sequence != self._dense_sequence or t_s > self._dense_until_s:
            return False
        last = self.db.last_of_sequence(self.sequence)
        interval = self.params.relocalization_keyframe_interval_s
        return last is None or t_s - last.t_s >= interval - 0.01  # 10 ms: frames arrive on control ticks

    def _start_sequence(self, t_s: float) -> None:
        # The correction in force stays the best guess until the new sequence relocalizes (an estimator that
        # coasts through a blackout keeps its frame).
        self.sequence = max([kf.sequence for kf in self.db.keyframes] + [self.sequence]) + 1
        self._dense_sequence, self._dense_until_s = self.sequence, np.inf
        self._lost = False
        self._path_m = self._path_at_anchor_m = 0.0
        self.gate.pending = None

    def _verify(self, kf: Keyframe, candidates: list[Keyframe], calib: CameraCalibration) -> list[Candidate]:
        """PnP-verify the candidates, check the first verified one against the drift bound, offer it."""
        self.gate.expire(kf.t_s)
        for match in candidates:
            verdict = verify_candidate(
                kf.keypoints_uv_px,
                kf.descriptors,
                kf.R_WB_odom,
                match,
                calib,
                self.params.keyframes,
                self.params.verification,
                kf.octaves,
            )
            if verdict.pose is None:
                continue
            if match.R_WB_map is not None:
                T = make_candidate(kf, match, verdict.pose, self.heading_axis_B).correction
                self.verified_corrections.append((kf.t_s, kf.sequence, match.index, kf.p_WB_odom, T))
            # An ill-conditioned pose is refused where the sequence has other loops to come (a relocalization
            # has none yet and relies on the confirmation).
            if self.localized and verdict.pose.yaw_sigma_deg > self.params.verification.max_yaw_sigma_deg:
                continue
            cand = make_candidate(kf, match, verdict.pose, self.heading_axis_B)
            if self.localized:
                predicted = RigidTransform(*self.blender.target.apply_pose(kf.R_WB_odom, kf.p_WB_odom))
                path_m = self._path_m - self._path_at_anchor_m
                if not self.gate.within_drift(cand, predicted, path_m, self.heading_axis_B):
                    continue
            return self.gate.confirm(cand, self.heading_axis_B)
        return []

    def _candidates(self, kf: Keyframe) -> list[Keyframe]:
        rp = self.params.recognition
        if self.bow is None:
            if len(self.db) + 1 < rp.vocabulary_train_keyframes:
                return []
            descs = np.vstack([k.descriptors for k in self.db.keyframes] + [kf.descriptors])
            vocab = train_vocabulary(descs, rp.vocabulary_size, rp.vocabulary_iterations, rp.seed)
            self.bow = BowDatabase(vocab)
            for old in self.db.keyframes:
                old.tf = self.bow.transform(old.descriptors)
                self.bow.add(old.tf)
        kf.tf = self.bow.transform(kf.descriptors)
        # A keyframe with fewer landmarks than PnP needs inliers cannot be verified: it is no candidate (in a
        # hover the keyframes have no baseline and none, and would crowd out those of the climb that have).
        min_landmarks = self.params.verification.min_inliers
        rows = np.array(
            [
                k.index
                for k in self.db.keyframes
                if k.sequence in self._localized
                and (k.sequence != kf.sequence or kf.t_s - k.t_s >= rp.min_time_gap_s)
                and int(np.count_nonzero(k.has_landmark)) >= min_landmarks
            ],
            dtype=np.int64,
        )
        if len(rows) == 0:
            return []
        scores = self.bow.scores(kf.tf, rows)
        order = np.argsort(-scores)[: rp.n_candidates]
        return [self.db.keyframes[rows[i]] for i in order if scores[i] >= rp.min_score]

    def _insert(self, kf: Keyframe, prev: Keyframe | None) -> None:
        self.db.add(kf)
        if self.bow is not None and kf.tf is not None:
            self.bow.add(kf.tf)
        if kf.sequence not in self._localized:
            return
        kf.R_WB_map, kf.p_WB_map = self.blender.target.apply_pose(kf.R_WB_odom, kf.p_WB_odom)
        self.graph.add_node(kf.index, self._yaw(kf.R_WB_map), kf.p_WB_map, fixed=len(self.graph) == 0)
        if prev is not None:
            self._odometry_edge(prev, kf)

    def _odometry_edge(self, prev: Keyframe, kf: Keyframe) -> None:
        meas = relative_4dof(prev.R_WB_odom, prev.p_WB_odom, kf.R_WB_odom, kf.p_WB_odom, self.heading_axis_B)
        self.graph.add_edge(Edge4Dof(prev.index, kf.index, *meas))

    def _close(self, accepted: list[Candidate]) -> LoopClosure:
        kf, match, verified = accepted[-1].query, accepted[-1].match, accepted[-1].verified
        T_mq = verified.T_match_query
        relocalization = kf.sequence not in self._localized
        if relocalization:  # align the whole sequence to the map where PnP puts the query
            T_map_q = RigidTransform(match.R_WB_map, match.p_WB_map) @ T_mq
            align = drift_4dof(T_map_q.R, T_map_q.p, kf.R_WB_odom, kf.p_WB_odom, self.heading_axis_B)
            members = [k for k in self.db.keyframes if k.sequence == kf.sequence]
            for i, k in enumerate(members):
                k.R_WB_map, k.p_WB_map = align.apply_pose(k.R_WB_odom, k.p_WB_odom)
                self.graph.add_node(k.index, self._yaw(k.R_WB_map), k.p_WB_map)
                if i > 0:
                    self._odometry_edge(members[i - 1], k)
            self._localized.add(kf.sequence)
            if kf.sequence == self._dense_sequence:
                self._dense_until_s = kf.t_s + self.params.relocalization_dense_s
        for c in accepted:
            meas = loop_4dof(c.match.R_WB_odom, c.verified.T_match_query, self.heading_axis_B)
            to_map = c.match.sequence < self._first_own_sequence
            self.graph.add_edge(Edge4Dof(c.match.index, c.query.index, *meas, is_loop=True, to_map=to_map))
        self.last_solve = self.graph.optimize()
        self._path_at_anchor_m = self._path_m
        for k in self.db.keyframes:
            if k.index in self.graph:
                yaw, p = self.graph.node(k.index)
                k.R_WB_map = rotz(yaw - self._yaw(k.R_WB_odom)) @ k.R_WB_odom
                k.p_WB_map = p
        # Localizing into a loaded map snaps (the odometry frame before was arbitrary: nothing to blend from);
        # every other correction is blended in.
        snap = relocalization and self._loaded_map and kf.sequence == self._first_own_sequence
        self.blender.set_target(
            kf.t_s,
            drift_4dof(kf.R_WB_map, kf.p_WB_map, kf.R_WB_odom, kf.p_WB_odom, self.heading_axis_B),
            snap=snap,
        )
        for i, c in enumerate(accepted):
            T = c.verified.T_match_query
            self.closures.append(
                LoopClosure(
                    c.query.t_s,
                    c.match.t_s,
                    T.p.copy(),
                    T.quat_xyzw(),
                    c.verified.inliers,
                    c.verified.rms_px,
                    relocalization and i == len(accepted) - 1,
                )
            )
        return self.closures[-1]

    def smoothed_corrections(self, times_s: np.ndarray) -> list[RigidTransform]:
        """The final (non-causal) correction at each time, from the pose graph as it stands now.

        Each time takes the correction ``T_map_odom`` of the localized keyframes around it (interpolated
        between the one before and the one after, of the same sequence); a time whose sequence never
        localized keeps the correction in force then (identity before any). This is the loop-closed
        trajectory of the whole run (VINS-Mono's pose-graph path), as opposed to ``corrected_pose``, which is
        what was known at the time.
        """
        own = self._first_own_sequence
        kfs = [k for k in self.db.keyframes if k.R_WB_map is not None and k.sequence >= own]
        if not kfs:
            return [self.correction(float(t)) for t in times_s]
        kf_t = np.array([k.t_s for k in kfs])
        axis = self.heading_axis_B
        corr = [drift_4dof(k.R_WB_map, k.p_WB_map, k.R_WB_odom, k.p_WB_odom, axis) for k in kfs]
        out = []
        for t in np.asarray(times_s, dtype=float):
            j = int(np.searchsorted(kf_t, t, side="right"))
            before, after = max(j - 1, 0), min(j, len(kfs) - 1)
            if kfs[before].sequence != kfs[after].sequence or before == after:
                out.append(corr[before] if t >= kf_t[before] else corr[after])
                continue
            alpha = float(np.clip((t - kf_t[before]) / (kf_t[after] - kf_t[before]), 0.0, 1.0))
            out.append(interpolate(corr[before], corr[after], alpha))
        return out

    def save_map(self, path: Path | str) -> None:
        """Write the localized keyframes, their edges, the vocabulary and the closures (see ``map_io``).

        Raises:
            ValueError: No vocabulary yet (fewer keyframes than ``vocabulary_train_keyframes``).
        """
        if self.bow is None:
            raise ValueError("no vocabulary yet: too few keyframes to save a map")
        kept = [k for k in self.db.keyframes if k.sequence in self._localized]
        write_map_arrays(
            path,
            map_arrays(
                kept,
                self.bow.vocabulary,
                self.heading_axis_B,
                self._map_edges + self.graph.edges,
                self.closures,
            ),
        )

    def load_map(self, path: Path | str) -> None:
        """Load a map into a fresh closer; the run localizes into the map frame at its first recognized place.

        Raises:
            ValueError: The closer already has keyframes.
        """
        if len(self.db):
            raise ValueError("load_map needs a fresh LoopCloser (it already has keyframes)")
        arrays = read_map_arrays(path)
        keyframes, edges, closures = keyframes_from_arrays(arrays)
        self.bow = BowDatabase(arrays["vocabulary"])
        self.heading_axis_B = arrays["heading_axis_B"].copy()
        for kf in keyframes:
            kf.tf = self.bow.transform(kf.descriptors)
            self.db.add(kf)
            self.bow.add(kf.tf)
            self.graph.add_node(kf.index, self._yaw(kf.R_WB_map), kf.p_WB_map, fixed=True)
        self._map_edges = edges
        self.closures = closures
        self._n_loaded_closures = len(closures)
        self._localized = {kf.sequence for kf in keyframes}
        self.sequence = max(self._localized, default=-1) + 1
        self._first_own_sequence = self.sequence
        self._loaded_map = True
