"""Simulation.step_checked's split step (mj_step2 after the last step's mj_forward) equals plain mj_step.

The reference steps a second copy of the model with ``mj_step(n)`` then ``mj_forward``, the form
``step_checked`` had before it reused the closing ``mj_forward``; both must agree bit for bit, on the ground
(contacts), in free flight with changing thrusts and wind, after ``set_pose`` and after a mass edit.
"""

import mujoco
import numpy as np
from viotb.envs.sim.simulation import Simulation


def _reference_step(sim: Simulation, ctrl: np.ndarray, n: int) -> None:
    sim.data.ctrl[:] = ctrl
    mujoco.mj_step(sim.model, sim.data, n)
    mujoco.mj_forward(sim.model, sim.data)


def _assert_same(a: Simulation, b: Simulation) -> None:
    for name in ("qpos", "qvel", "qacc", "sensordata", "actuator_force", "xpos", "qacc_warmstart"):
        np.testing.assert_array_equal(getattr(a.data, name), getattr(b.data, name), err_msg=name)
    assert a.data.time == b.data.time and a.data.ncon == b.data.ncon


def test_split_step_equals_mj_step_on_the_ground_in_flight_and_after_edits():
    rng = np.random.default_rng(0)
    new, ref = Simulation("quadrotor", "textured_room"), Simulation("quadrotor", "textured_room")
    body = new._body_id
    contacts_seen, z_max = 0, 0.0
    for k in range(400):
        if k < 60:
            thrust = np.full(4, 1.0)  # resting on the floor: contacts
        else:
            thrust = 3.2 + 0.4 * rng.standard_normal(4)
        force = rng.normal(scale=0.5, size=3)
        n = int(rng.integers(1, 6))
        for sim in (new, ref):
            sim.data.xfrc_applied[body, :3] = force
        new.step_checked(new.checked_ctrl(thrust), n)
        _reference_step(ref, thrust, n)
        _assert_same(new, ref)
        contacts_seen += new.data.ncon > 0
        z_max = max(z_max, float(new.data.qpos[2]))
        if k == 200:
            R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
            for sim in (new, ref):
                sim.set_pose(R, np.array([0.3, -0.2, 1.5]), np.array([0.1, 0.0, -0.2]))
        if k == 300:
            for sim in (new, ref):
                sim.model.body_mass[body] *= 1.1
                sim.model.body_inertia[body] *= 1.1
                mujoco.mj_setConst(sim.model, sim.data)
            new.model_changed()
    assert contacts_seen >= 50 and z_max > 1.0  # both regimes were stepped
