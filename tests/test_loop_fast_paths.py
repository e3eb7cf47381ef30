"""The closed loop's per-tick float paths equal the numpy forms they replaced, bit for bit.

Each fast path below (controllers, sensors, simulation readers) keeps the floating-point operations of the
array form and their order; these tests hold it to that form (copied here where the module no longer has
it), signs of zeros included where a later operation could see them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from viotb.controllers.profiles import min_jerk_segment
from viotb.controllers.setpoints import Sequence, Waypoints
from viotb.controllers.types import FlatOutput
from viotb.envs.sim.checks import all_finite, norm3
from viotb.envs.sim.imu_model import _quantize, _quantize_f
from viotb.envs.sim.simulation import Simulation
from viotb.vio.lie import quat_wxyz_to_rotmat, quat_wxyz_to_rotmat_rows


def _same_bits(a, b) -> bool:
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return a.shape == b.shape and a.tobytes() == b.tobytes()


def test_quantize_f_equals_array_quantize_with_the_sign_of_zero():
    rng = np.random.default_rng(0)
    step = 0.0006981317007977319  # the adis16448 gyro step
    x = np.concatenate(
        [
            rng.normal(scale=0.01, size=20000),
            rng.normal(scale=step, size=20000),  # many round to a signed zero
            (np.arange(-50, 50) + 0.5) * step,  # halfway cases: rint rounds half to even
            [0.0, -0.0, 1e-300, -1e-300],
        ]
    )
    want = _quantize(x, step)
    got = np.array([_quantize_f(v, step) for v in x.tolist()])
    assert _same_bits(got, want)
    assert np.signbit(want).sum() > 0 and np.sum(want == 0.0) > 100
    assert _quantize_f(-0.25, 0.0) == -0.25  # no quantization


def test_flat_output_from_floats_equals_the_validating_constructor():
    rng = np.random.default_rng(1)
    for _ in range(200):
        p, v, a, j = (rng.normal(size=3).tolist() for _ in range(4))
        yaw, rate = rng.normal(size=2).tolist()
        fast = FlatOutput.from_floats(p, v, a, j, yaw, rate)
        slow = FlatOutput(p_W=p, v_W=v, a_W=a, j_W=j, yaw_rad=yaw, yaw_rate_rad_s=rate)
        for name in ("p_W", "v_W", "a_W", "j_W"):
            arr = getattr(fast, name)
            assert _same_bits(arr, getattr(slow, name)) and not arr.flags.writeable and arr.dtype == float
        assert (fast.yaw_rad, fast.yaw_rate_rad_s) == (slow.yaw_rad, slow.yaw_rate_rad_s)
    with pytest.raises(ValueError, match="a_W"):
        FlatOutput.from_floats([0.0] * 3, [0.0] * 3, [0.0, math.nan, 0.0], [0.0] * 3, 0.0, 0.0)
    with pytest.raises(ValueError, match="yaw_rate_rad_s"):
        FlatOutput.from_floats([0.0] * 3, [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, math.inf)
    with pytest.raises(ValueError, match="v_W"):
        FlatOutput.from_floats([0.0] * 3, [0.0] * 4, [0.0] * 3, [0.0] * 2, 0.0, 0.0)
    big = FlatOutput.from_floats([1e308, 1e308, 0.0], [0.0] * 3, [0.0] * 3, [0.0] * 3, 0.0, 0.0)
    assert big.p_W.tolist() == [1e308, 1e308, 0.0]  # the sum overflows, the entries are finite


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_all_finite_and_norm3_equal_numpy():
    rng = np.random.default_rng(2)
    for _ in range(2000):
        x = rng.normal(size=rng.integers(1, 8)) * 10.0 ** rng.integers(-5, 309)
        if rng.random() < 0.3:
            x[rng.integers(len(x))] = rng.choice([math.nan, math.inf, -math.inf])
        assert all_finite(x.tolist()) == bool(np.isfinite(x).all())
        if np.isfinite(x).all() and len(x) == 3:
            assert _same_bits(norm3(x), float(np.linalg.norm(x)))
    assert all_finite([1e308, 1e308]) and not all_finite([math.inf, -math.inf])


def _old_quat_wxyz_to_rotmat(q):
    """The form before ``quat_wxyz_to_rotmat_rows``: numpy's normalisation, then the products in floats."""
    q = np.asarray(q, dtype=float).ravel()
    w, x, y, z = (q / np.sqrt(q.dot(q))).tolist()
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def test_quaternion_rows_equal_the_former_matrix():
    rng = np.random.default_rng(3)
    for _ in range(20000):
        q = rng.normal(size=4) * 10.0 ** rng.uniform(-3, 3)
        R = quat_wxyz_to_rotmat(q)
        assert _same_bits(R, _old_quat_wxyz_to_rotmat(q)) and R.shape == (3, 3)
        assert _same_bits(quat_wxyz_to_rotmat_rows(q), R.ravel())
    with np.errstate(invalid="ignore"):
        assert np.isnan(quat_wxyz_to_rotmat(np.zeros(4))).all()  # numpy's 0 / 0, not an exception


@pytest.mark.parametrize("vehicle", ["quadrotor", "headset"])
def test_body_state_equals_the_readers(vehicle):
    sim = Simulation(vehicle, "textured_room")
    rng = np.random.default_rng(4)
    for _ in range(20):
        R = quat_wxyz_to_rotmat(rng.normal(size=4))
        sim.set_pose(R, rng.normal(size=3) + [0.0, 0.0, 1.5], rng.normal(size=3), rng.normal(size=3))
        if vehicle == "quadrotor":
            sim.step(np.full(4, 3.0), 3)
        got = sim.body_state()
        R_WB, p_WB = sim.pose()
        want = (R_WB, p_WB, sim.velocity_W(), sim.angular_velocity_B())
        for g, w in zip(got, want, strict=True):
            assert _same_bits(g, w) and not g.flags.writeable


def _old_waypoint_sample(wp: Waypoints, t_s: float) -> FlatOutput:
    """Waypoints.sample before the bisection on lists (np.searchsorted on the arrays)."""
    t = min(max(float(t_s), 0.0), wp.duration_s)
    k = int(np.clip(np.searchsorted(wp._starts, t, side="right") - 1, 0, len(wp._times) - 1))
    return min_jerk_segment(
        wp._points[k], wp._points[k + 1], float(wp._yaws[k]), float(wp._yaws[k + 1]), float(wp._times[k]),
        t - float(wp._starts[k]),
    )  # fmt: skip


def test_waypoints_and_sequence_lookup_equal_searchsorted():
    rng = np.random.default_rng(5)
    wp = Waypoints(
        rng.normal(size=(6, 3)), yaws_rad=rng.normal(size=6), segment_times_s=rng.uniform(0.5, 2, 5)
    )
    ts = np.concatenate([rng.uniform(-1.0, wp.duration_s + 1.0, 500), wp._starts, [wp.duration_s, -0.0]])
    for t in ts.tolist():
        a, b = wp.sample(t), _old_waypoint_sample(wp, t)
        for name in ("p_W", "v_W", "a_W", "j_W"):
            assert _same_bits(getattr(a, name), getattr(b, name))
        assert (a.yaw_rad, a.yaw_rate_rad_s) == (b.yaw_rad, b.yaw_rate_rad_s)
    seq = Sequence([wp, Waypoints(np.stack([wp._points[-1], [0.0, 0.0, 1.0]]), segment_times_s=[1.5])])
    for t in np.concatenate([rng.uniform(-1.0, seq.duration_s + 1.0, 300), seq.start_times_s]).tolist():
        k = max(0, int(np.searchsorted(seq.start_times_s, t, side="right")) - 1)
        want = seq._items[k].sample(t - seq.start_times_s[k])
        assert _same_bits(seq.sample(t).p_W, want.p_W) and _same_bits(seq.sample(t).j_W, want.j_W)


def test_flat_output_vector_floats_are_the_array_values():
    for fo in (
        FlatOutput(p_W=[1, 2, 3], v_W=np.array([0.5, -0.0, 2.0]), yaw_rad=0.3),
        FlatOutput.from_floats([1.0, 2.0, 3.0], [0.5, -0.0, 2.0], [0, 0, 0], [0.0, 1e-300, -4.0], 0.3, 0.0),
    ):
        want = np.concatenate([fo.p_W, fo.v_W, fo.a_W, fo.j_W])
        got = fo.vector_floats
        assert type(got) is tuple and all(type(x) is float for x in got)
        assert _same_bits(got, want)
