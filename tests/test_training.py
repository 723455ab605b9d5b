"""Training on data labelled by the true field: learning, determinism, early stopping, flight splits."""

import dataclasses
import importlib.util
import multiprocessing
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from downwash.datasets import Dataset, split_by_flight
from downwash_core.errors import DataError
from downwash.models import EquivariantModel
from downwash.train import TrainConfig, predict, rmse, torch_kernels, train_model
from downwash_core.numerics import PORTABLE_TORCH
from sim.field import DownwashField


def field_dataset(n, rng, n_flights=10, noise=0.05, stage=0):
    """n samples below a level leader, labelled by the true mean field plus white noise (m/s^2).

    Each flight is a contiguous block of samples (a flight id per block).
    """
    dp = np.column_stack([rng.uniform(-0.8, 0.8, (n, 2)), -rng.uniform(0.3, 1.6, n)])
    speed, heading = rng.uniform(0, 1.0, n), rng.uniform(-np.pi, np.pi, n)
    v_b = np.column_stack([speed * np.cos(heading), speed * np.sin(heading), rng.normal(0, 0.1, n)])
    v_a = rng.normal(0, 0.05, (n, 3))
    R = np.broadcast_to(np.eye(3), (n, 3, 3)).copy()
    truth = DownwashField()(np.zeros(3), v_a, R, dp, v_b)
    y = truth + noise * rng.normal(size=(n, 3))
    return Dataset.from_pairs(dp, v_a, v_b, R, y, np.arange(n) * n_flights // n, np.full(n, stage),
                              np.arange(n) * 0.02, truth)


FAST = TrainConfig(max_epochs=40, min_steps=0, batch_size=512, patience=40)


def test_equivariant_model_learns_the_field():
    train = field_dataset(8000, np.random.default_rng(0))
    val = field_dataset(3000, np.random.default_rng(1))
    model, hist = train_model("equivariant", train, None, FAST)
    overall, per_axis = rmse(model, val)
    label_std = float(np.sqrt(np.mean((val.y - val.y.mean(0)) ** 2)))
    assert label_std > 0.2
    assert overall < 0.45 * label_std, (overall, label_std)
    assert per_axis.shape == (3,) and np.all(per_axis < 0.45 * np.sqrt(np.mean((val.y - val.y.mean(0)) ** 2, axis=0)) + 0.06)
    # against the noise-free truth the error is below the label noise (0.05 per axis) plus a margin
    truth_rmse, _ = rmse(model, dataclasses.replace(val, y=val.field_mean))
    assert truth_rmse < 0.1
    assert hist["kind"] == "equivariant" and hist["lr"] == EquivariantModel.default_lr == 5e-2
    assert hist["val_loss"][hist["best_epoch"]] == hist["best_val_loss"] == min(hist["val_loss"])
    pred = predict(model, val)
    assert pred.shape == (3000, 3) and pred.dtype == np.float64


def test_same_seed_gives_bit_identical_weights():
    data = field_dataset(2000, np.random.default_rng(2))
    config = TrainConfig(max_epochs=3, min_steps=0, batch_size=256, seed=7)
    weights = {}
    for kind in ("equivariant", "deep"):
        a, ha = train_model(kind, data, None, config)
        b, hb = train_model(kind, data, None, config)
        sa, sb = a.state_dict(), b.state_dict()
        assert sa.keys() == sb.keys()
        for k in sa:
            assert torch.equal(sa[k], sb[k]), k
        assert ha["val_loss"] == hb["val_loss"]
        weights[kind] = sa
    c, _ = train_model("equivariant", data, None, dataclasses.replace(config, seed=8))
    assert not torch.equal(c.state_dict()["net.0.weight"], weights["equivariant"]["net.0.weight"])


def test_global_rng_untouched():
    data = field_dataset(500, np.random.default_rng(3), n_flights=4)
    torch.manual_seed(123)
    expected = torch.rand(3)
    torch.manual_seed(123)
    train_model("shallow", data, None, TrainConfig(max_epochs=1, min_steps=0))
    assert torch.equal(torch.rand(3), expected)


def test_early_stopping_restores_the_best_epoch():
    """Validation labels opposite to the training labels: val loss rises as training fits."""
    train = field_dataset(3000, np.random.default_rng(4))
    val = dataclasses.replace(train, y=-train.y)
    config = TrainConfig(max_epochs=30, min_steps=0, batch_size=256, patience=3, lr=3e-3)
    model, hist = train_model("equivariant", train, val, config)
    assert hist["epochs"] < 30  # stopped early
    assert hist["best_epoch"] == int(np.argmin(hist["val_loss"]))
    assert hist["epochs"] - 1 - hist["best_epoch"] == 3  # patience 3 (30 planned epochs = max_epochs)
    restored = rmse(model, val)[0] ** 2
    assert restored == pytest.approx(hist["val_loss"][hist["best_epoch"]], rel=1e-5)
    assert restored < hist["val_loss"][-1]


def test_split_by_flight_never_mixes_flights():
    data = field_dataset(6000, np.random.default_rng(5), n_flights=12)
    _, hist = train_model("shallow", data, None, TrainConfig(max_epochs=1, min_steps=0, val_fraction=0.25))
    assert hist["train_flights"] and hist["val_flights"]
    assert set(hist["train_flights"]).isdisjoint(hist["val_flights"])
    assert set(hist["train_flights"]) | set(hist["val_flights"]) == set(range(12))
    for seed in range(5):
        tr, va = split_by_flight(data, 0.3, np.random.default_rng(seed))
        assert set(np.unique(tr.flight)).isdisjoint(np.unique(va.flight))
        assert len(tr) + len(va) == len(data)
        assert 0.2 < len(va) / len(data) < 0.45


def test_train_config_and_input_errors():
    with pytest.raises(ValueError, match=r"TrainConfig.batch_size: expected an int >= 1, got 0"):
        TrainConfig(batch_size=0)
    with pytest.raises(ValueError, match=r"TrainConfig.lr: expected None or > 0, got -1"):
        TrainConfig(lr=-1)
    with pytest.raises(ValueError, match=r"TrainConfig.val_fraction: expected in \(0, 1\), got 1.5"):
        TrainConfig(val_fraction=1.5)
    data = field_dataset(400, np.random.default_rng(6), n_flights=1)
    with pytest.raises(ValueError, match="need at least 2 flights"):
        train_model("equivariant", data, None, FAST)
    with pytest.raises(ValueError, match="model kind: unknown 'linear'; allowed: shallow, deep"):
        train_model("linear", field_dataset(400, np.random.default_rng(6), n_flights=2), None, FAST)
    bad = dataclasses.replace(data, y=np.full((400, 3), np.nan))
    with pytest.raises(ValueError, match=r"train.y: contains non-finite values"):
        train_model("equivariant", bad, data, FAST)
    fields = {f.name: getattr(data, f.name) for f in dataclasses.fields(data)}
    with pytest.raises(TypeError, match=r"val: expected a downwash.datasets.Dataset, got SimpleNamespace"):
        train_model("equivariant", data, SimpleNamespace(**fields), FAST)
    with pytest.raises(ValueError, match=r"Dataset.dp: expected shape \(400, 1, 3\), got \(400, 1, 2\)"):
        dataclasses.replace(data, dp=np.zeros((400, 1, 2)))


def test_trainings_in_forked_processes_equal_trainings_here():
    """The staged collection trains its final models one forked process per core at once
    (`downwash.staged._in_parallel`): each model is bit-identical to one trained in this process
    (even after this process trained with torch), and a child's error names its item."""
    from downwash.staged import _in_parallel

    data = field_dataset(2000, np.random.default_rng(4))
    config = TrainConfig(max_epochs=3, min_steps=0, batch_size=256, seed=3)

    def weights(kind: str) -> dict:
        model, history = train_model(kind, data, None, config)
        return {"state": {k: v.numpy().tobytes() for k, v in model.state_dict().items()}, "epochs": history["epochs"]}

    kinds = ["deep", "equivariant", "shallow"]
    here = {kind: weights(kind) for kind in kinds}
    forked = dict(_in_parallel(weights, kinds))
    assert forked == here

    def fails(item: str) -> dict:
        if item == "b":
            raise ValueError("boom in b")
        return {}

    with pytest.raises(RuntimeError, match="(?s)b: .*boom in b"):
        list(_in_parallel(fails, ["a", "b"]))

    # inside a daemonic process (which may not have children) it trains one after another instead
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=lambda: queue.put(dict(_in_parallel(weights, ["shallow", "equivariant"]))),
                       daemon=True)
    proc.start()
    assert queue.get(timeout=120) == {kind: here[kind] for kind in ("shallow", "equivariant")}
    proc.join()


def test_logs_flown_with_and_without_wind_never_mix(tmp_path):
    """The pair data set checks the wind as the swarm data set does (the two had diverged)."""
    from downwash.datasets import load_dataset
    from sim.flight import fly
    from sim.logs import save_log
    from sim.scene import build_scene
    from sim.wind import DrydenWind
    from downwash_trajectories import Hover, Lemniscate, stack

    leader = np.array([0.0, 0.0, 2.5])
    reference = stack([Hover(leader, n_worlds=1), Lemniscate(leader - [0, 0, 0.6], n_worlds=1)])
    still = fly(build_scene(), reference, [0], 1.0)[0]
    windy = fly(build_scene(), reference, [1], 1.0, wind=DrydenWind(mean=(1.0, 0.0, 0.0)))[0]
    for name, log in (("still", still), ("windy", windy)):
        (tmp_path / name).mkdir()
        save_log(tmp_path / name / "flight_000.npz", log)
    assert load_dataset(tmp_path / "still").provenance["wind"] is None
    assert load_dataset(tmp_path / "windy").provenance["wind"] is not None
    with pytest.raises(DataError, match="wind"):
        load_dataset([tmp_path / "still" / "flight_000.npz", tmp_path / "windy" / "flight_000.npz"])


_spec = importlib.util.spec_from_file_location("golden_machine", Path(__file__).parent / "golden" / "machine.py")
golden_machine = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(golden_machine)


def test_training_runs_and_records_the_portable_kernels():
    """Asked for before torch ran here (tests/conftest.py, as the experiments do): a CPU with AVX2
    trains with them, and each history says which kernels trained it."""
    _, hist = train_model("shallow", field_dataset(600, np.random.default_rng(7), n_flights=3), None,
                          dataclasses.replace(FAST, max_epochs=2))
    assert hist["kernels"] == torch_kernels() and hist["config"]["portable"] is True
    if golden_machine.runs_portable_torch():
        assert hist["kernels"] == {"aten": "AVX2", "mkl_cbwr": "AVX2"}


def test_training_warns_once_when_torch_runs_other_kernels():
    """A process whose environment chose other kernels (kept: the user's) trains with them and says so, once."""
    code = ("import logging, torch; logging.basicConfig(); torch.ones(4).sum()\n"
            "from downwash.train import TrainConfig, training_kernels\n"
            "print(training_kernels(TrainConfig())['aten'], training_kernels(TrainConfig())['aten'],"
            " training_kernels(TrainConfig(portable=False))['aten'])")
    env = {k: v for k, v in os.environ.items() if k not in PORTABLE_TORCH}
    env["ATEN_CPU_CAPABILITY"] = "default"
    proc = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=300, check=True)
    assert proc.stdout.split() == ["DEFAULT"] * 3
    assert proc.stderr.count("training with this CPU's torch kernels") == 1
    assert "ATEN_CPU_CAPABILITY=avx2 MKL_CBWR=AVX2" in proc.stderr
    with pytest.raises(ValueError, match=r"TrainConfig.portable: expected True or False, got 'yes'"):
        TrainConfig(portable="yes")
