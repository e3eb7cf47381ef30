"""The consistency gate after PnP: loops the odometry or the next keyframe contradict are not accepted.

A verified loop that puts the query elsewhere than the odometry's drift allows, or that the next keyframe
does not confirm, is not accepted.

The "look-alike place elsewhere" is built on purpose: the candidate's PnP pose is geometrically perfect (as a
repeated pillar or a copy of the same poster gives) but the match keyframe stands 1.5 m away from where the
query really revisits, so the loop would teleport the query by 1.5 m.
"""

from __future__ import annotations

import numpy as np
from viotb.vio.lie import rotz
from viotb.vio.loop.consistency import ConsistencyGate, make_candidate
from viotb.vio.loop.frames import X_AXIS, RigidTransform
from viotb.vio.loop.keyframes import Keyframe
from viotb.vio.loop.params import ConsistencyParams
from viotb.vio.loop.verification import VerifiedPose


def _kf(index: int, t_s: float, yaw_deg: float, p, sequence: int = 0, mapped: bool = True) -> Keyframe:
    R = rotz(np.deg2rad(yaw_deg))
    p = np.asarray(p, dtype=float)
    empty = np.zeros((0, 2), np.float32), np.zeros((0, 32), np.uint8), np.zeros((0, 3))
    kf = Keyframe(index, t_s, sequence, R, p, *empty)
    if mapped:
        kf.R_WB_map, kf.p_WB_map = R.copy(), p.copy()
    return kf


def _loop(query: Keyframe, match: Keyframe, T_true_map_q: RigidTransform, shift=(0.0, 0.0, 0.0)):
    """A verified pose that puts the query at ``T_true_map_q`` shifted by ``shift`` (m) in the map."""
    T_map_q = RigidTransform(T_true_map_q.R, T_true_map_q.p + np.asarray(shift))
    T_mq = RigidTransform(match.R_WB_map, match.p_WB_map).inverse() @ T_map_q
    return make_candidate(query, match, VerifiedPose(T_mq, 120, 200, 0.6), X_AXIS)


def test_look_alike_place_elsewhere_is_refused_by_the_drift_bound():
    gate = ConsistencyGate(ConsistencyParams())
    match = _kf(0, 0.0, 0.0, [0.0, 0.0, 1.0])
    query = _kf(50, 20.0, 2.0, [0.05, 0.02, 1.0])  # odometry says: back at the start, 5 cm of drift
    predicted = RigidTransform(query.R_WB_odom, query.p_WB_odom)
    truth = RigidTransform(rotz(np.deg2rad(1.5)), np.array([0.02, 0.0, 1.0]))
    right = _loop(query, match, truth)
    wrong = _loop(query, match, truth, shift=(1.5, 0.0, 0.0))  # a look-alike 1.5 m away
    assert gate.within_drift(right, predicted, path_m=20.0, axis_B=X_AXIS)
    assert not gate.within_drift(wrong, predicted, path_m=20.0, axis_B=X_AXIS)
    assert gate.rejected_drift == 1


def test_a_candidate_needs_the_next_keyframe_to_agree():
    gate = ConsistencyGate(ConsistencyParams())
    match_a, match_b = _kf(0, 0.0, 0.0, [0.0, 0.0, 1.0]), _kf(1, 0.3, 0.0, [0.3, 0.0, 1.0])
    # The odometry drifted by the same 4-DOF offset at both queries (0.3 m apart, 0.35 s apart).
    drift = RigidTransform.from_yaw(np.deg2rad(3.0), np.array([0.2, -0.1, 0.05]))
    truths = [
        RigidTransform(np.eye(3), np.array([0.02, 0.0, 1.0])),
        RigidTransform(np.eye(3), [0.32, 0, 1.0]),
    ]
    odo = [drift @ t for t in truths]
    q1 = _kf(60, 20.0, 0.0, odo[0].p, mapped=False)
    q1.R_WB_odom = odo[0].R
    q2 = _kf(61, 20.35, 0.0, odo[1].p, mapped=False)
    q2.R_WB_odom = odo[1].R
    assert gate.confirm(_loop(q1, match_a, truths[0]), X_AXIS) == []  # held, not accepted
    accepted = gate.confirm(_loop(q2, match_b, truths[1]), X_AXIS)
    assert [c.query.index for c in accepted] == [60, 61]
    # A look-alike at the second keyframe (0.5 m off) does not confirm the first, nor is it accepted itself.
    gate = ConsistencyGate(ConsistencyParams())
    assert gate.confirm(_loop(q1, match_a, truths[0]), X_AXIS) == []
    assert gate.confirm(_loop(q2, match_b, truths[1], shift=(0.0, 0.5, 0.0)), X_AXIS) == []
    assert gate.unconfirmed == 1


def test_a_stale_candidate_expires():
    gate = ConsistencyGate(ConsistencyParams(confirm_window_s=3.0))
    match = _kf(0, 0.0, 0.0, [0.0, 0.0, 1.0])
    q1 = _kf(60, 20.0, 0.0, [0.0, 0.0, 1.0], mapped=False)
    assert gate.confirm(_loop(q1, match, RigidTransform(np.eye(3), np.array([0.0, 0.0, 1.0]))), X_AXIS) == []
    gate.expire(24.0)
    assert gate.pending is None and gate.unconfirmed == 1


def _revisit(n: int, spacing_s: float = 0.35):
    """``n`` query keyframes 0.3 m apart with the same odometry drift, their matches and true map poses."""
    drift = RigidTransform.from_yaw(np.deg2rad(3.0), np.array([0.2, -0.1, 0.05]))
    out = []
    for i in range(n):
        truth = RigidTransform(np.eye(3), np.array([0.02 + 0.3 * i, 0.0, 1.0]))
        odo = drift @ truth
        q = _kf(60 + i, 20.0 + spacing_s * i, 0.0, odo.p, mapped=False)
        q.R_WB_odom = odo.R
        out.append((q, _kf(i, 0.3 * i, 0.0, [0.3 * i, 0.0, 1.0]), truth))
    return out


def test_the_latest_accepted_loop_confirms_the_next_candidate_at_once():
    (q1, m1, t1), (q2, m2, t2), (q3, m3, t3) = _revisit(3)
    gate = ConsistencyGate(ConsistencyParams())
    assert gate.confirm(_loop(q1, m1, t1), X_AXIS) == []
    assert len(gate.confirm(_loop(q2, m2, t2), X_AXIS)) == 2  # the pair
    # The third agrees with the accepted second: accepted at its own keyframe, nothing left pending.
    assert [c.query.index for c in gate.confirm(_loop(q3, m3, t3), X_AXIS)] == [62]
    assert gate.pending is None
    # A look-alike 0.5 m off at the third keyframe is not accepted by the accepted loop: it is held.
    gate = ConsistencyGate(ConsistencyParams())
    gate.confirm(_loop(q1, m1, t1), X_AXIS)
    gate.confirm(_loop(q2, m2, t2), X_AXIS)
    wrong = _loop(q3, m3, t3, shift=(0.0, 0.5, 0.0))
    assert gate.confirm(wrong, X_AXIS) == [] and gate.pending is wrong
    # Without the rule, the third waits for a fourth as before.
    gate = ConsistencyGate(ConsistencyParams(confirm_by_accepted=False))
    gate.confirm(_loop(q1, m1, t1), X_AXIS)
    gate.confirm(_loop(q2, m2, t2), X_AXIS)
    assert gate.confirm(_loop(q3, m3, t3), X_AXIS) == []


def test_an_accepted_loop_confirms_only_within_the_window_and_its_sequence():
    (q1, m1, t1), (q2, m2, t2), (q3, m3, t3) = _revisit(3, spacing_s=2.0)
    gate = ConsistencyGate(ConsistencyParams(confirm_window_s=3.0))
    gate.confirm(_loop(q1, m1, t1), X_AXIS)
    gate.confirm(_loop(q2, m2, t2), X_AXIS)
    q3.t_s = q2.t_s + 3.5  # later than the window after the accepted loop
    assert gate.confirm(_loop(q3, m3, t3), X_AXIS) == []
    gate = ConsistencyGate(ConsistencyParams())
    gate.confirm(_loop(q1, m1, t1), X_AXIS)
    gate.confirm(_loop(q2, m2, t2), X_AXIS)
    q3.t_s, q3.sequence = q2.t_s + 0.35, 1  # a new odometry sequence (after a tracking loss)
    assert gate.confirm(_loop(q3, m3, t3), X_AXIS) == []
