"""The recipes of docs/extending.md, run as written: a new field, a new model kind and a new
controller each do what the page says they do (a recipe that drifts from the code fails here)."""

import sys

import numpy as np
import pytest

from experiments.benchmark.recipes import docs_blocks as _blocks  # the page's python blocks, by section

LEADER = np.array([0.0, 0.0, 2.5])


def _flight(duration=2.0, **components):
    from sim.flight import fly
    from sim.scene import build_scene
    from downwash_trajectories import Hover, stack

    reference = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)])
    return fly(build_scene(), reference, [0], duration, **components)[0]


def _fused_equals_readable(sims, n_ticks=40, reset_at=15):
    """Tick a fused and a readable simulator of the same worlds side by side, world 1 reset at tick
    `reset_at` (None: never): every tick's rows are equal bit for bit. Returns the last tick's rows."""
    assert sims[0]._plan is not None and sims[1]._plan is None
    for k in range(n_ticks):
        if k == reset_at:
            for sim in sims:
                sim.reset(np.array([1]))
        rows = [dict(sim.tick()) for sim in sims]
        assert all(np.array_equal(rows[0][name], rows[1][name], equal_nan=True) for name in rows[0])
    return rows


def test_the_field_recipe_flies_by_import_path(tmp_path, monkeypatch):
    from experiments.common import load_field

    code = _blocks("A new field")[1]
    assert code.startswith("# mypkg/fields.py")
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text("")
    (tmp_path / "mypkg" / "fields.py").write_text(code)
    monkeypatch.syspath_prepend(str(tmp_path))
    field = load_field("mypkg.fields:make")  # checked as --field checks it
    log = _flight(field=field)
    assert log.ok
    follower = int(log.meta["follower"])
    assert log["field_mean"][:, follower, 2].mean() < -1.0  # the jet pushes the follower down
    sys.modules.pop("mypkg.fields", None), sys.modules.pop("mypkg", None)


def test_the_compiled_field_recipe_flies_the_fused_tick_as_the_readable_path(tmp_path, monkeypatch):
    """The page's Gaussian jet with a compiled form, in modules of their own (numba caches by file): its simulator
    takes the fused tick, both paths fly the same bits, and the compiled sum is the NumPy law to rounding."""
    from sim.field import pairwise_field
    from sim.simulator import Simulator
    from sim.scene import build_scene
    from downwash_trajectories import Hover, Lemniscate, stack

    blocks = _blocks("A new field")
    assert blocks[3].startswith("# mypkg/compiled_fields.py")
    (tmp_path / "mypkg").mkdir()
    (tmp_path / "mypkg" / "__init__.py").write_text("")
    (tmp_path / "mypkg" / "fields.py").write_text(blocks[1])
    (tmp_path / "mypkg" / "compiled_fields.py").write_text(blocks[3])
    monkeypatch.syspath_prepend(str(tmp_path))
    for name in ("mypkg.compiled_fields", "mypkg.fields", "mypkg"):
        monkeypatch.delitem(sys.modules, name, raising=False)  # (and restored after the test)
    from mypkg.compiled_fields import CompiledGaussianJet

    field = CompiledGaussianJet()
    reference = stack([Hover(LEADER, n_worlds=3), Lemniscate(LEADER - [0, 0, 0.6], 0.1, 0.05, n_worlds=3)])
    sims = [Simulator(build_scene(), reference, [0, 1, 2], field=field, fast=fast) for fast in (True, False)]
    rows = _fused_equals_readable(sims)
    assert rows[0]["field_mean"][:, 1, 2].mean() < -1.0  # the jet pushes the follower down
    state = sims[0].true_states()
    np.testing.assert_allclose(field.pairwise(state.pos, state.vel, state.rot),
                               pairwise_field(lambda *args: field(*args), state.pos, state.vel, state.rot),
                               rtol=1e-12, atol=1e-12)


def _field_samples(n, rng):
    """n samples below a level leader labelled by the default field plus noise, in 10 flights."""
    from downwash.datasets import Dataset
    from sim.field import DownwashField

    dp = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), -rng.uniform(0.3, 1.6, n)])
    v_b, v_a = rng.normal(0, 0.3, (n, 3)), rng.normal(0, 0.05, (n, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    truth = DownwashField()(np.zeros(3), v_a, R, dp, v_b)
    return Dataset.from_pairs(dp, v_a, v_b, R, truth + 0.05 * rng.normal(size=(n, 3)), np.arange(n) * 10 // n,
                              t=np.arange(n) * 0.02, field_mean=truth)


def test_the_model_recipe_trains_saves_loads_and_flies_two_vehicles_and_many(tmp_path):
    """The page's one file registers the new kind; it trains on pair data, round-trips a
    checkpoint, flies two vehicles on both backends with the same prediction, and many vehicles as
    a model of sets (wrap_pairwise) with the same prediction as the plain sum over neighbours."""
    import torch

    import downwash.registry as registry
    import downwash.train as train
    from downwash.checkpoint import load_checkpoint, save_checkpoint, wrap_pairwise
    from downwash.predictor import LearnedPredictor
    from downwash_core.state import VehicleStates
    from sim.neighbours import NeighbourSet

    namespace: dict = {}
    exec(_blocks("A new model")[0], namespace)
    cls = namespace["WideEquivariant"]
    try:
        assert registry.MODEL_KINDS[cls.kind] is cls and registry.PAIRWISE_KINDS[cls.kind] is cls
        torch.manual_seed(0)
        data = _field_samples(3000, np.random.default_rng(0))
        model, history = train.train_model(cls.kind, data, None, train.TrainConfig(max_epochs=3, min_steps=0))
        assert history["lr"] == 5e-2
        path = tmp_path / "wide.pt"
        save_checkpoint(path, model, {})
        loaded, _ = load_checkpoint(path, expect_kind=cls.kind)
        assert isinstance(loaded, cls) and loaded.hidden == (64, 64)
        rng = np.random.default_rng(1)
        pos = np.stack([np.broadcast_to(LEADER, (4, 3)), LEADER + rng.uniform(-0.3, 0.3, (4, 3)) - [0, 0, 0.7]], 1)
        states = VehicleStates(pos, rng.normal(0, 0.2, (4, 2, 3)), np.broadcast_to(np.eye(3), (4, 2, 3, 3)).copy())
        compiled = LearnedPredictor(loaded)(states, states)
        readable = LearnedPredictor(loaded, backend="numpy")(states, states)
        assert np.abs(compiled).max() > 0.1
        np.testing.assert_allclose(compiled, readable, rtol=0, atol=1e-9)
        # many vehicles: a stack of four, each vehicle summing its two nearest neighbours above it
        stack = LEADER - np.array([[0, 0, 0], [0.05, 0, 0.5], [-0.05, 0.05, 1.0], [0, -0.05, 1.5]])
        many = VehicleStates(np.broadcast_to(stack, (2, 4, 3)).copy(), np.zeros((2, 4, 3)),
                             np.broadcast_to(np.eye(3), (2, 4, 3, 3)).copy())
        swarm = wrap_pairwise(path, NeighbourSet(2))
        got = LearnedPredictor(swarm)(many, many)
        pair = loaded.numpy_forward()
        want = np.zeros((4, 3))
        for j in range(4):
            near = sorted((i for i in range(4) if i != j), key=lambda i: (np.linalg.norm(stack[j] - stack[i]), i))[:2]
            for i in near:
                want[j] += pair(stack[j] - stack[i], np.zeros(3), np.zeros(3), np.eye(3))
        np.testing.assert_allclose(got, np.broadcast_to(want, (2, 4, 3)), rtol=0, atol=1e-9)
        assert np.abs(want[3]).max() > 0.1 and (want[0] == 0).all()  # the bottom one feels wakes; the top none
    finally:
        registry.MODEL_KINDS.pop(cls.kind, None)
        registry.PAIRWISE_KINDS.pop(cls.kind, None)


def test_a_model_of_other_layers_flies_its_torch_model_as_the_page_says(tmp_path):
    """The recipe's model with a Tanh and a LayerNorm (layers the NumPy twin and the compiled pass do not
    have): trained, checkpointed, and flown by LearnedPredictor on its torch form, the prediction its own."""
    import torch
    from torch import nn

    import downwash.registry as registry
    import downwash.train as train
    from downwash.checkpoint import load_checkpoint, save_checkpoint
    from downwash.models import DownwashModel
    from downwash.predictor import LearnedPredictor
    from downwash_core.errors import ConfigError
    from downwash_core.state import VehicleStates

    class SmoothEquivariant(DownwashModel):
        kind = "equivariant_smooth"
        ALLOWED_FEATURE_SETS = ("5", "6")
        DEFAULT_FEATURE_SET = "5"
        n_outputs = 2
        default_lr = 5e-2

        def __init__(self, feature_set=None):
            super().__init__(feature_set)
            self.net = nn.Sequential(nn.Linear(self.n_features, 32), nn.LayerNorm(32), nn.Tanh(), nn.Linear(32, 2))

        def architecture(self):
            return {}

    registry.register(SmoothEquivariant)
    try:
        torch.manual_seed(0)
        model, _ = train.train_model("equivariant_smooth", _field_samples(3000, np.random.default_rng(0)), None,
                                     train.TrainConfig(max_epochs=3, min_steps=0))
        save_checkpoint(tmp_path / "smooth.pt", model, {})
        loaded, _ = load_checkpoint(tmp_path / "smooth.pt", expect_kind="equivariant_smooth")
        predictor = LearnedPredictor(loaded)
        assert predictor.backend == "torch"  # the page's promise: no twin, no compiled pass, the torch model
        for backend in ("compiled", "numpy"):  # refused, naming the one that runs it
            with pytest.raises(ConfigError, match="use 'torch'"):
                LearnedPredictor(loaded, backend=backend)
        rng = np.random.default_rng(1)
        pos = np.stack([np.broadcast_to(LEADER, (4, 3)), LEADER + rng.uniform(-0.3, 0.3, (4, 3)) - [0, 0, 0.7]], 1)
        states = VehicleStates(pos, rng.normal(0, 0.2, (4, 2, 3)), np.broadcast_to(np.eye(3), (4, 2, 3, 3)).copy())
        got = predictor(states, states)
        with torch.no_grad():  # the follower's prediction: the model on its pair with the leader
            own = loaded.double()(*(torch.as_tensor(x) for x in (pos[:, 1] - pos[:, 0], states.vel[:, 0],
                                                               states.vel[:, 1], states.rot[:, 0]))).numpy()
        np.testing.assert_allclose(got[:, 1], own, rtol=1e-9, atol=1e-9)
        assert np.abs(got[:, 1]).max() > 0.1 and (got[:, 0] == 0).all()  # the leader feels no wake from below
        log = _flight(2.0, predictor=LearnedPredictor(loaded))  # and it flies, on the readable path
        assert log.ok and np.abs(log["f_hat"][-10:, int(log.meta["follower"])]).max() > 0.1
    finally:
        registry.MODEL_KINDS.pop("equivariant_smooth", None)
        registry.PAIRWISE_KINDS.pop("equivariant_smooth", None)


def test_the_controller_recipe_flies_a_hover(monkeypatch):
    blocks = _blocks("A new controller")
    namespace: dict = {}
    exec(blocks[1], namespace)
    log = _flight(8.0, controller=namespace["PDController"]())
    assert log.ok and log.meta["controller"]["type"] == "PDController"
    follower = int(log.meta["follower"])
    # a PD loop has no integral: in steady state it sags by the wake's push over kp (analytic)
    sag = np.mean(log["pos"][-100:, follower, 2] - (LEADER[2] - 0.6))
    push = np.mean(log["field_mean"][-100:, follower, 2])
    assert sag < -0.1 and sag == pytest.approx(push / 4.0, rel=0.1)
    assert np.abs(log["pos"][-50:, follower, :2]).max() < 0.02  # and holds its place across
    assert "fly(scene, reference" in blocks[2]  # the call the page shows


def test_the_compiled_controller_recipe_flies_the_fused_tick_as_the_readable_path(tmp_path, monkeypatch):
    """The compiled PD of the page, in a module of its own (numba caches by file): its simulator takes the
    fused tick, and both paths fly the same bits."""
    import importlib

    from sim.scene import build_scene
    from sim.simulator import Simulator
    from downwash_trajectories import Hover, Lemniscate, stack

    (tmp_path / "recipe_compiled_pd.py").write_text(_blocks("A new controller")[3])
    monkeypatch.syspath_prepend(str(tmp_path))
    namespace = vars(importlib.import_module("recipe_compiled_pd"))
    reference = stack([Hover(LEADER, n_worlds=3), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=3)])
    sims = [Simulator(build_scene(), reference, [0, 1, 2], controller=namespace["CompiledPD"](), fast=fast)
            for fast in (True, False)]
    _fused_equals_readable(sims, n_ticks=50, reset_at=None)
    assert np.all(sims[0].controller.memory[..., 0] == 50)


def test_the_sensor_recipe_registers_and_flies_a_shared_offset(monkeypatch, request):
    """The frame-shifted motion capture, registered and flown as the page shows (shortened to 2 s):
    every vehicle's measurement is off by one offset, its episode's, on the fused path."""
    import sim.sensors as sensors
    from sim.flight import fly
    from sim.scene import build_scene
    from sim.simulator import SimConfig, Simulator
    from downwash_trajectories import Hover, stack

    blocks = _blocks("A new sensor noise model")
    assert blocks[1].startswith("# mypkg/sensors.py")
    namespace: dict = {"__name__": "mypkg.sensors"}
    exec(blocks[1], namespace)
    cls = namespace["FrameShiftedMocap"]
    request.addfinalizer(lambda: sensors.SENSORS.pop("mocap_frame_shift", None))  # the registration stays in this test
    scene = build_scene()
    reference = stack([Hover(LEADER, n_worlds=2), Hover(LEADER - [0, 0, 0.6], n_worlds=2)])
    run = {"SimConfig": SimConfig, "FrameShiftedMocap": cls, "scene": scene, "reference": reference,
           "fly": lambda *args, duration, **kw: fly(*args, duration=2.0, **kw)}
    exec(blocks[2], run)
    sensor = run["config"].mocap
    assert type(sensor) is cls and sensor.frame_offset == 0.005
    assert Simulator(scene, reference, [0, 1], config=run["config"])._plan is not None  # the fused tick flies it
    for log, seed in zip(run["logs"], (0, 1)):
        offset = sensors.draw_episode_offset(sensor, seed, 2)
        assert np.array_equal(offset[0], offset[1]) and np.abs(offset).max() > 0.001
        error = (log["mocap_pos"] - log["pos"]).mean(axis=0)  # (V, 3): the offset, and white noise averaged
        np.testing.assert_allclose(error, offset, rtol=0, atol=4 * sensor.position_noise / np.sqrt(len(log)))
        assert log.meta["config"]["mocap"] == {"type": "mypkg.sensors.FrameShiftedMocap", "position_noise": 0.0005,
                                              "attitude_noise": 0.002, "process_accel_noise": 2.0,
                                              "frame_offset": 0.005}
    with pytest.raises(ValueError, match=r"mocap_frame_shift frame_offset: allowed 0.0 to 0.05 m"):
        cls(frame_offset=0.1)


def test_the_compiled_sensor_recipe_flies_the_fused_tick_as_the_readable_path(tmp_path, monkeypatch):
    """The page's dropout sensor, in a module of its own (numba caches by file): it flies the fused tick, both
    paths fly the same bits, the page's flight runs (shortened to 2 s), and without losses it is `mocap`."""
    import importlib

    from sim.flight import fly
    from sim.scene import build_scene
    from sim.simulator import SimConfig, Simulator
    from downwash_trajectories import Hover, Lemniscate, stack

    blocks = _blocks("A new sensor noise model")
    assert blocks[3].startswith("# mypkg/dropouts.py")
    (tmp_path / "recipe_dropout_mocap.py").write_text(blocks[3])
    monkeypatch.syspath_prepend(str(tmp_path))
    cls = vars(importlib.import_module("recipe_dropout_mocap"))["DropoutMocap"]
    scene = build_scene()
    reference = stack([Hover(LEADER, n_worlds=3), Lemniscate(LEADER - [0, 0, 0.6], n_worlds=3)])
    config = SimConfig(mocap=cls(loss=0.4))
    sims = [Simulator(scene, reference, [0, 1, 2], config=config, fast=fast) for fast in (True, False)]
    _fused_equals_readable(sims)
    pair = stack([Hover(LEADER, n_worlds=2), Hover(LEADER - [0, 0, 0.6], n_worlds=2)])  # the page's two seeds
    run = {"SimConfig": SimConfig, "DropoutMocap": cls, "scene": scene, "reference": pair,
           "fly": lambda *args, duration, **kw: fly(*args, duration=2.0, **kw)}
    exec(blocks[4], run)
    assert run["logs"][0].ok and run["logs"][0].meta["config"]["mocap"]["loss"] == 0.2
    plain = fly(scene, reference, [0, 1, 2], 1.0)
    for a, b in zip(plain, fly(scene, reference, [0, 1, 2], 1.0, config=SimConfig(mocap=cls(loss=0.0)))):
        assert np.array_equal(a["mocap_pos"], b["mocap_pos"]) and np.array_equal(a["pos"], b["pos"])
