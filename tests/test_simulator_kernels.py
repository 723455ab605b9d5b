"""One compilation per variant: flights of every kind compile each kernel of the loop only as often as
its argument types must differ.

A second signature of a kernel is a second compilation (seconds per fresh build, 15 s for the fused
tick): an argument that is an int in one call and a float in another, or C-contiguous in one and
strided in another, compiles the kernel again without any error. These tests fly the fused and the
readable path, serial and batched, with and without wind, with the zero, oracle, learned, guarded and
per-world predictors, actions and a batch stepped by the caller, and count the signatures each kernel of
`sim.passes` and `sim.fused` holds afterwards.

Each path flies in a process of its own, so that the counts do not depend on the order of the tests,
nor on numba's disk cache: a kernel that another kernel calls gets a signature for each such call
when the caller is compiled, but none when the caller is loaded from the cache. The readable path
never touches the fused kernel, so its process counts exactly the passes the simulator calls from
Python; the fused kernel is never called by another kernel, so its count is exact in any process.
"""

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent

# The physics state arrays come in two layouts: a single world's MjData (C-contiguous) and the rows of
# a `mujoco.batch.Batch` (strided). Every kernel that takes them compiles once per layout; every
# other kernel once. Nothing else may add a signature.
PHYSICS_LAYOUTS = 2
READABLE = {  # the passes the readable path calls from Python (and `Simulator.true_states`)
    "sense_kernel": PHYSICS_LAYOUTS, "actuate_kernel": PHYSICS_LAYOUTS, "status_kernel": PHYSICS_LAYOUTS,
    "wind_force_kernel": PHYSICS_LAYOUTS, "true_states_kernel": PHYSICS_LAYOUTS,
    "hold_kernel": 1, "wind_sense_kernel": 1, "wind_advance_kernel": 1,
}
FUSED = {"FUSED_KERNELS[0]": PHYSICS_LAYOUTS, "FUSED_KERNELS[1]": PHYSICS_LAYOUTS}  # without, with wind
# When this process compiles the fused kernel (its cache is stale or absent), each pass it calls gains
# one signature per physics layout at most (one chunk's slices of the state arrays); loaded from the
# cache, none.
FUSED_CALLEES_AT_MOST = {
    "sense_kernel": PHYSICS_LAYOUTS, "actuate_kernel": PHYSICS_LAYOUTS, "status_kernel": PHYSICS_LAYOUTS,
    "sense_law_kernel": PHYSICS_LAYOUTS,  # (a sensor's compiled law, sim.sensor_contract: typed, never run here)
    "read_truth": PHYSICS_LAYOUTS,  # (both sensing passes', inlined)
    "wind_force_kernel": PHYSICS_LAYOUTS, "hold_kernel": PHYSICS_LAYOUTS, "wind_sense_kernel": PHYSICS_LAYOUTS,
    "wind_advance_kernel": PHYSICS_LAYOUTS, "_step_rows": 1, "_copy_into": 1, "_row_view": 1,
    "true_states_kernel": PHYSICS_LAYOUTS,  # (`Simulator.true_states`, from Python)
    "_published": 1,
    # the stages (sim.tick_stages): those given the physics state, or the velocities relative to the air
    # (with wind: the wind's buffer; without: the row's), once per layout of it; the others once
    "sense_stage": PHYSICS_LAYOUTS, "actuate_stage": PHYSICS_LAYOUTS, "wind_force_stage": PHYSICS_LAYOUTS,
    "monitor_stage": PHYSICS_LAYOUTS, "predict_stage": 2, "_predict_world": 2, "field_stage": 2, "wind_stage": 1,
    "control_stage": 1, "physics_stage": 1,
    # the bundle makers once each; the table's typed views once per shape tuple's type (its constants' too)
    **dict.fromkeys(("world_bundle", "vehicles_bundle", "inputs_bundle", "buffers_bundle", "wind_bundle",
                     "prediction_bundle", "control_bundle", "stepping_bundle", "monitor_bundle", "_i64"), 1),
    "_f64": 10,
}


def fly_and_count(fast: bool) -> dict[str, int]:
    """Fly every kind of flight on one path; {kernel: number of signatures} of the passes and the fused
    kernels afterwards (run in a fresh process: see the module docstring)."""
    import numpy as np
    from numba.core.registry import CPUDispatcher

    from downwash.guard import GuardedPredictor
    from downwash.registry import make_model
    from downwash.predictor import LearnedPredictor
    from downwash.support import SUPPORT_FEATURES, Support
    from downwash_trajectories import Hover, Lemniscate, stack
    from sim import fused, passes, tick_stages
    from sim.field import DownwashField
    from sim.fused_abi import STEP_CALLER, STEP_ROWS, STEP_SERIAL
    from sim.predictor import OraclePredictor, PerWorldPredictor, ZeroPredictor
    from sim.scene import build_scene
    from sim.simulator import Simulator
    from sim.wind import DrydenWind

    leader = np.array([0.0, 0.0, 2.5])
    scene = build_scene()
    learned = LearnedPredictor(make_model("equivariant", "5"))
    F = len(SUPPORT_FEATURES)
    support = Support(np.full(F, -0.5), np.full(F, 0.5), np.full(F, 0.25))  # (partly inside: fractions in (0, 1))
    for wind in (None, DrydenWind(mean=(1.0, 0.0, 0.0), w20=4.0)):
        for W, n_threads in ((1, 1), (8, 2)):  # serial; batched on two threads (helpers on the fused path)
            predictors = [ZeroPredictor(), OraclePredictor(DownwashField()), learned,
                          PerWorldPredictor([ZeroPredictor(), OraclePredictor(DownwashField()), learned],
                                            np.arange(W) % 3), GuardedPredictor(learned, support)]
            for predictor in predictors:
                ref = stack([Hover(leader, n_worlds=W), Lemniscate(leader - [0, 0, 0.6], n_worlds=W)])
                sim = Simulator(scene, ref, list(range(W)), predictor=predictor, wind=wind, fast=fast,
                                n_threads=n_threads)
                assert (sim._plan is not None) == fast
                if fast:
                    assert sim._plan.stepping == (STEP_SERIAL if W == 1 else STEP_ROWS)
                V = sim.V
                for k in range(12):  # 4 predictor periods; actions as the envs give them, one not C-ordered
                    residual = np.full((W, V, 3), 0.1) if k % 3 == 1 else None
                    override = np.full((V, 3, W), np.nan).transpose(2, 0, 1) if k % 3 == 2 else None
                    sim.tick(residual=residual, override=override)
                sim.true_states()
                if W > 1:  # worlds with models of their own: the batch steps them between autopilot ticks
                    sim.physics.set_body_mass(np.array([0]), scene.body_ids[1:], np.array([[0.8]]))
                    for _ in range(3):
                        sim.tick()
                    assert not fast or sim._plan.stepping == STEP_CALLER
    counts = {}
    for module in (passes, fused, tick_stages):
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and obj.py_func.__module__ == module.__name__:
                counts[name] = len(obj.signatures)
    for i, kernel in enumerate(fused.FUSED_KERNELS):
        counts[f"FUSED_KERNELS[{i}]"] = len(kernel.signatures)
    return counts


def _counts_in_a_fresh_process(fast: bool) -> dict[str, int]:
    code = ("import json, sys; sys.path.insert(0, 'tests'); from test_simulator_kernels import fly_and_count; "
            f"print(json.dumps(fly_and_count({fast})))")
    proc = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-4000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])


def test_the_readable_path_compiles_each_pass_once_per_physics_layout():
    counts = _counts_in_a_fresh_process(fast=False)
    got = {name: counts[name] for name in READABLE}
    assert got == READABLE, f"a pass was compiled for more argument types than expected: {got}"
    assert counts["FUSED_KERNELS[0]"] == counts["FUSED_KERNELS[1]"] == 0


def test_the_fused_path_compiles_each_variant_once_per_physics_layout():
    counts = _counts_in_a_fresh_process(fast=True)
    got = {name: counts[name] for name in FUSED}
    assert got == FUSED, f"a fused kernel was compiled for more argument types than expected: {got}"
    over = {name: counts[name] for name, most in FUSED_CALLEES_AT_MOST.items() if counts[name] > most}
    assert not over, f"the fused kernel called a pass with more argument types than expected: {over}"
    # every kernel of the two modules is counted by one of the tests
    assert set(counts) == set(READABLE) | set(FUSED) | set(FUSED_CALLEES_AT_MOST)
