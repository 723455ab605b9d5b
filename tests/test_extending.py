"""The recipes of docs/extending.md, run as written: a new field, a new model kind and a new
controller each do what the page says they do (a recipe that drifts from the code fails here)."""

import re
import sys
from pathlib import Path

import numpy as np
import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "extending.md"
LEADER = np.array([0.0, 0.0, 2.5])


def _blocks(section: str) -> list[str]:
    """The python code blocks of a `## section` of the page, in order (indented ones included)."""
    text = DOC.read_text()
    body = text.split(f"## {section}\n", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"^( *)```python\n(.*?)^\1```", body, flags=re.S | re.M)
    return [re.sub(rf"(?m)^{indent}", "", code) for indent, code in blocks]


def _flight(duration=2.0, **components):
    from sim.flight import fly
    from sim.scene import build_scene
    from downwash_trajectories import Hover, stack

    reference = stack([Hover(LEADER, n_worlds=1), Hover(LEADER - [0, 0, 0.6], n_worlds=1)])
    return fly(build_scene(), reference, [0], duration, **components)[0]


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


def _field_samples(n, rng):
    """n samples below a level leader labelled by the default field plus noise, in 10 flights."""
    from downwash.datasets import Dataset
    from sim.field import DownwashField

    dp = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), -rng.uniform(0.3, 1.6, n)])
    v_b, v_a = rng.normal(0, 0.3, (n, 3)), rng.normal(0, 0.05, (n, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    truth = DownwashField()(np.zeros(3), v_a, R, dp, v_b)
    return Dataset(dp=dp, v_a=v_a, v_b=v_b, R_a=R, y=truth + 0.05 * rng.normal(size=(n, 3)),
                   flight=np.arange(n) * 10 // n, stage=np.zeros(n, int), t=np.arange(n) * 0.02, field_mean=truth)


def test_the_model_recipe_trains_saves_loads_and_flies(tmp_path, monkeypatch):
    """Registered as the page says (MODEL_KINDS, DEFAULT_LR), the new kind trains, round-trips a
    checkpoint, and flies in the predictor slot on both backends with the same prediction."""
    import torch
    from torch import nn

    import downwash.models as models
    import downwash.train as train
    from downwash.checkpoint import load_checkpoint, save_checkpoint
    from downwash.predictor import LearnedPredictor
    from downwash_core.state import VehicleStates

    namespace = {"nn": nn, "DownwashModel": models.DownwashModel}
    exec(_blocks("A new model")[0], namespace)
    cls = namespace["WideEquivariant"]
    monkeypatch.setitem(models.MODEL_KINDS, cls.kind, cls)
    monkeypatch.setitem(train.DEFAULT_LR, cls.kind, 5e-2)
    torch.manual_seed(0)
    data = _field_samples(3000, np.random.default_rng(0))
    model, history = train.train_model(cls.kind, data, None, train.TrainConfig(max_epochs=3, min_steps=0))
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
