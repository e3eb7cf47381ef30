"""Consistency of a verified loop with the odometry, and its confirmation by a later keyframe.

PnP verification alone let a closure 0.48 m off through on a flat textured wall (lateral translation and
rotation trade off on a plane) and cannot tell two alike places of a repetitive scene apart. Two checks follow
it, both on the query's map pose that the closure implies, ``T_map_q = T_map_match @ T_match_query``:

1. Drift bound (sequences already in the map frame): the query's map pose predicted by the correction in force
   (``T_map_odom @ T_odom_q``) can be off only by the drift accumulated since the last accepted closure of
   the sequence (or its start), so the two must agree within ``base + rate * path`` in position and yaw,
   where ``path`` is the odometry's travelled distance since then.
2. Confirmation: a candidate is held until a later keyframe of the same sequence, at most ``window_s``
   later, is verified too (optionally against another keyframe than the held one's match:
   ``confirm_distinct_match``), and both imply the same drift correction: the later query's
   map pose predicted with the earlier candidate's correction must agree with its own within ``confirm_*``.
   A place that only looks alike rarely gives two consistent poses in a row; relocalization (no prediction
   to check against) relies on this alone. With ``confirm_by_accepted``, the sequence's latest accepted
   loop, at most ``window_s`` earlier, confirms a new candidate by the same test: while the loops of a
   revisit keep agreeing, each is accepted at its own keyframe instead of waiting for the next one (which
   never comes for the last keyframe of a run, where a drone lands back at its start).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from viotb.vio.loop.frames import RigidTransform, drift_4dof, heading_rad, wrap_angle
from viotb.vio.loop.keyframes import Keyframe
from viotb.vio.loop.params import ConsistencyParams
from viotb.vio.loop.verification import VerifiedPose


@dataclass(frozen=True)
class Candidate:
    """A verified but not yet accepted loop.

    Attributes:
        query: The query keyframe.
        match: The matched keyframe (in the map frame).
        verified: The PnP result.
        T_map_query: The query's map pose that the loop implies.
        correction: The 4-DOF ``T_map_odom`` that the loop implies for the query's sequence.
    """

    query: Keyframe
    match: Keyframe
    verified: VerifiedPose
    T_map_query: RigidTransform
    correction: RigidTransform


def pose_gap(T_a: RigidTransform, T_b: RigidTransform, axis_B: np.ndarray) -> tuple[float, float]:
    """Position distance (m) and absolute heading difference (deg) of two body poses."""
    dyaw = wrap_angle(heading_rad(T_a.R, axis_B) - heading_rad(T_b.R, axis_B))
    return float(np.linalg.norm(T_a.p - T_b.p)), float(abs(np.rad2deg(dyaw)))


def make_candidate(query: Keyframe, match: Keyframe, verified: VerifiedPose, axis_B: np.ndarray) -> Candidate:
    """The candidate of a verified loop (``match`` must have a map pose)."""
    T_map_q = RigidTransform(match.R_WB_map, match.p_WB_map) @ verified.T_match_query
    correction = drift_4dof(T_map_q.R, T_map_q.p, query.R_WB_odom, query.p_WB_odom, axis_B)
    return Candidate(query, match, verified, T_map_q, correction)


class ConsistencyGate:
    """Drift-bound check and confirmation of loop candidates (see the module docstring).

    Args:
        params: Bounds and tolerances.
    """

    def __init__(self, params: ConsistencyParams | None = None) -> None:
        """No candidate pending."""
        self.params = params or ConsistencyParams()
        self.pending: Candidate | None = None
        self.last_accepted: Candidate | None = None
        self.rejected_drift = 0
        self.unconfirmed = 0

    def within_drift(
        self, cand: Candidate, predicted: RigidTransform, path_m: float, axis_B: np.ndarray
    ) -> bool:
        """Whether the loop's query pose agrees with the predicted one within the drift bound."""
        cp = self.params
        gap_m, gap_deg = pose_gap(cand.T_map_query, predicted, axis_B)
        ok = (
            gap_m <= cp.drift_base_m + cp.drift_rate_m_per_m * path_m
            and gap_deg <= cp.drift_base_deg + cp.drift_rate_deg_per_m * path_m
        )
        self.rejected_drift += not ok
        return ok

    def _agrees(self, earlier: Candidate, cand: Candidate, axis_B: np.ndarray) -> bool:
        """Whether two loops of one sequence, at most ``confirm_window_s`` apart, imply one correction."""
        cp = self.params
        if earlier.query.sequence != cand.query.sequence:
            return False
        if cand.query.t_s - earlier.query.t_s > cp.confirm_window_s:
            return False
        predicted = RigidTransform(*earlier.correction.apply_pose(cand.query.R_WB_odom, cand.query.p_WB_odom))
        gap_m, gap_deg = pose_gap(cand.T_map_query, predicted, axis_B)
        return gap_m <= cp.confirm_translation_m and gap_deg <= cp.confirm_yaw_deg

    def confirm(self, cand: Candidate, axis_B: np.ndarray) -> list[Candidate]:
        """Offer a candidate; returns the candidates accepted now (none, this one, or the pending one and it).

        With ``confirmations == 0`` every candidate is accepted at once. Otherwise the pending candidate
        confirms it (both are accepted), else the latest accepted loop does (``confirm_by_accepted``: it
        alone is accepted, and a pending candidate that it did not confirm is dropped), else it is held.
        """
        cp = self.params
        if cp.confirmations == 0:
            return [cand]
        prev = self.pending
        self.pending = cand
        if prev is not None and prev.query.sequence == cand.query.sequence:
            if cp.confirm_distinct_match and prev.match.index == cand.match.index:
                self.pending = prev if cand.query.t_s - prev.query.t_s <= cp.confirm_window_s else cand
                return self._by_accepted(cand, axis_B)
            if self._agrees(prev, cand, axis_B):
                self.pending = None
                self.last_accepted = cand
                return [prev, cand]
            self.unconfirmed += 1
        return self._by_accepted(cand, axis_B)

    def _by_accepted(self, cand: Candidate, axis_B: np.ndarray) -> list[Candidate]:
        """``[cand]`` when the latest accepted loop confirms it (``confirm_by_accepted``), else ``[]``."""
        last = self.last_accepted
        if not self.params.confirm_by_accepted or last is None or not self._agrees(last, cand, axis_B):
            return []
        if self.pending is not cand:  # a held candidate (distinct-match rule) that this one outlives
            self.unconfirmed += 1
        self.pending = None
        self.last_accepted = cand
        return [cand]

    def expire(self, t_s: float) -> None:
        """Drop a pending candidate older than ``confirm_window_s`` at ``t_s``."""
        if self.pending is not None and t_s - self.pending.query.t_s > self.params.confirm_window_s:
            self.pending = None
            self.unconfirmed += 1
