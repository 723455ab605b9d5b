"""The compiled-controller contract (`controllers.compiled`): the lab controllers and a user's controller
fly the fused tick, bit for bit as their readable path, with resets, actions and chunks of worlds."""

import numpy as np
import pytest

from controllers.compiled import CompiledController, controller_function, finish_one, run_step
from controllers.crazyflie import CrazyfliePID, MellingerController
from controllers.indi import INDIController
from controllers.lqr import attitude_setpoint
from downwash_core.errors import ConfigError
from downwash_core.jit import njit
from downwash_trajectories import Hover, Lemniscate, stack
from sim.scene import build_scene
from sim.simulator import Simulator
from sim.safety import SafetyConfig

LEADER = np.array([0.0, 0.0, 2.5])


@pytest.fixture(scope="module")
def scene():
    return build_scene()


def _reference(W):
    return stack([Hover(LEADER, n_worlds=W), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=W)])


def _fly(scene, make, W, n_ticks, fast, **kw):
    """The rows of a flight of W worlds, with world 1 reset a third of the way and actions on every other tick."""
    sim = Simulator(scene, _reference(W), list(range(W)), controller=make(), fast=fast, **kw)
    rng = np.random.default_rng(3)
    rows = []
    for k in range(n_ticks):
        if k == n_ticks // 3 and W > 1:
            sim.reset(np.array([1]))
        residual = rng.normal(0.0, 0.3, (W, 2, 3)) if k % 2 else None
        override = np.full((W, 2, 3), np.nan)
        override[:, 1, 2] = 0.5 if k % 3 == 0 else np.nan  # a vertical command on some ticks, free on the others
        rows.append(dict(sim.tick(residual=residual, override=override if k % 3 == 0 else None)))
    return rows, sim


def _assert_same(a, b):
    (rows_a, sim_a), (rows_b, sim_b) = a, b
    for k, (x, y) in enumerate(zip(rows_a, rows_b)):
        for name in x:
            assert np.array_equal(x[name], y[name], equal_nan=True), (k, name)
    assert np.array_equal(sim_a.physics.qpos, sim_b.physics.qpos)


@pytest.mark.parametrize("make", [MellingerController, CrazyfliePID, INDIController], ids=["mellinger", "pid", "indi"])
@pytest.mark.parametrize("W", [1, 12])  # 12: chunks of worlds on two threads, offsets into the controller's memory
def test_lab_controllers_fly_fused_as_readable(scene, make, W):
    fused = _fly(scene, make, W, 60, fast=True)
    assert fused[1]._plan is not None, "the compiled form was expected to fly the fused tick"
    readable = _fly(scene, make, W, 60, fast=False)
    _assert_same(fused, readable)
    # the memory is the controller's own: the fused flight advanced it and a reset clears it
    memory = fused[1].controller.compiled_controller(W, 2).state
    assert np.any(memory != 0.0)
    fused[1].controller.reset(np.array([0]))
    assert np.all(memory[0] == 0.0)


# the docs' recipe (docs/extending.md, "A new controller"): a PD law with one body for both paths
@njit
def pd_step(pos, vel, yaw, ref_pos, ref_vel, ref_acc, ref_yaw, ref_yaw_rate, f_hat, residual, override, use_residual,
            use_override, lookahead, state, params, acc, yaw_rate, thrust, rot):
    kp, kd, tan_tilt, min_vertical = params[0], params[1], params[2], params[3]
    for w in range(pos.shape[0]):
        for i in range(pos.shape[1]):
            for k in range(3):
                e_p, e_v = pos[w, i, k] - ref_pos[w, i, k], vel[w, i, k] - ref_vel[w, i, k]
                acc[w, i, k] = ref_acc[w, i, k] - kp * e_p - kd * e_v - f_hat[w, i, k]
            state[w, i, 0] += 1.0  # ticks since the world's reset: memory, as an integrator keeps it
            yaw_rate[w, i] = ref_yaw_rate[w, i]
            yaw_des = ref_yaw[w, i] + ref_yaw_rate[w, i] * lookahead
            thrust[w, i] = finish_one(acc, w, i, residual, override, use_residual, use_override, yaw_des, tan_tilt,
                                      min_vertical, rot)


class CompiledPD:
    """A PD controller with a compiled form: params (kp, kd, tan(max tilt), min vertical), memory (W, V, 1)."""

    function = None  # the C function, compiled once for the class

    def __init__(self, kp=4.0, kd=3.0):
        self.params = np.array([kp, kd, np.tan(np.radians(35.0)), 0.25 * 9.81])
        self.memory = np.zeros((0, 0, 1))

    def describe(self):
        return {"type": "CompiledPD", "kp": float(self.params[0]), "kd": float(self.params[1])}

    def _memory(self, W, V):
        if self.memory.shape[:2] != (W, V):
            self.memory = np.zeros((W, V, 1))
        return self.memory

    def reset(self, worlds=None):
        if len(self.memory):  # (none before its first tick)
            self.memory[slice(None) if worlds is None else worlds] = 0.0

    def command_setpoint(self, state, ref, f_hat, out, residual=None, override=None, lookahead=0.0):
        run_step(pd_step, state, ref, f_hat, out, residual, override, lookahead, self._memory(*state.pos.shape[:2]),
                 self.params)

    def compiled_controller(self, W, V):
        if CompiledPD.function is None:
            CompiledPD.function = controller_function(pd_step, 1, len(self.params))
        return CompiledController(CompiledPD.function.address, self.params, self._memory(W, V))


class ReadablePD:
    """The same law in NumPy (the recipe's readable controller, no compiled form)."""

    def __init__(self, kp=4.0, kd=3.0):
        self.kp, self.kd = kp, kd

    def describe(self):
        return {"type": "ReadablePD"}

    def command_setpoint(self, state, ref, f_hat, out, residual=None, override=None, lookahead=0.0):
        acc = ref.acc - self.kp * (state.pos - ref.pos) - self.kd * (state.vel - ref.vel) - f_hat
        if residual is not None:
            acc = acc + residual
        if override is not None:
            acc = np.where(np.isfinite(override), override, acc)
        thrust, rot = attitude_setpoint(acc, ref.yaw + ref.yaw_rate * lookahead)
        out.acc[:] = acc
        out.yaw_rate[:] = ref.yaw_rate
        out.thrust[:] = thrust
        out.rot[:] = rot


@pytest.mark.parametrize("W", [1, 12])
def test_a_users_compiled_controller_flies_fused_as_readable(scene, W):
    fused = _fly(scene, CompiledPD, W, 60, fast=True)
    assert fused[1]._plan is not None
    _assert_same(fused, _fly(scene, CompiledPD, W, 60, fast=False))
    # its memory counted the ticks since each world's reset, in the fused tick as on the readable path
    memory = fused[1].controller.memory[..., 0]
    assert memory[0, 0] == 60 and (W == 1 or memory[1, 0] == 60 - 20)


def test_the_compiled_pd_computes_the_numpy_law(scene):
    """The compiled recipe and the NumPy one are the same law: one tick from the same state agrees to rounding."""
    rows_c, _ = _fly(scene, CompiledPD, 4, 1, fast=True)
    rows_r, _ = _fly(scene, ReadablePD, 4, 1, fast=False)
    for name in ("u_cmd", "pos"):
        np.testing.assert_allclose(rows_c[0][name], rows_r[0][name], rtol=0, atol=1e-12)


def test_a_compiled_form_with_a_wrong_memory_is_refused_before_flight(scene):
    class Bad(CompiledPD):
        def compiled_controller(self, W, V):
            return super().compiled_controller(W, V)._replace(state=np.zeros((W, V, 2))[..., :1])  # not contiguous

    with pytest.raises(ConfigError, match="C-contiguous float64"):
        Simulator(scene, _reference(2), [0, 1], controller=Bad(), fast=True)


def test_with_the_safety_layer_a_compiled_form_flies_the_readable_path(scene):
    sim = Simulator(scene, _reference(2), [0, 1], controller=MellingerController(), safety=SafetyConfig())
    assert sim._plan is None
