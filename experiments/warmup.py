"""Compile the simulator's kernels ahead, so that the first flight or env `reset()` starts at once.

    python -m experiments.warmup [--quick]      # or: downwash-warmup

The kernels (numba) compile on their first use after an install or an update, once, and are
cached on disk (`downwash_core.jit`); the first flight otherwise waits for them (about half a
minute to a few minutes on two cores) with a one-line notice. This command flies, for a few
controller periods each, every combination the experiments and the envs use: a pair flight
with no model, with the true field, and with each learned model kind (untrained: the kernels
depend on the kind, not on its weights), guarded and not, on each compiled field, with and
without wind; the single and vector follower envs; the swarm env (with the multiagent extra).
It prints what it compiled and how long each took. A second run takes seconds.
"""

from __future__ import annotations

import argparse
import time
from typing import Any, Callable, Sequence

import numpy as np

from experiments.common import OneLineParser, run_main, script

FIELDS = ("so2", "momentum", "shed")  # the compiled field families the experiments fly
MODEL_KINDS = ("shallow", "deep", "equivariant", "equivariant_general", "deepsets_equivariant", "deepsets")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m experiments.warmup", description=__doc__.split("\n\n")[0],
                           allow_abbrev=False)
    parser.add_argument("--quick", action="store_true",
                        help="compile only what the lemniscate experiment and the follower env use")
    parser.add_argument("--debug", action="store_true", help="tracebacks for expected errors")
    return parser


def _pair_flight(field: str = "so2", predictor: Any = None, wind: bool = False, oracle: bool = False) -> None:
    from downwash_core.params import LEADER_POSITION
    from downwash_trajectories import Hover, Transect, stack
    from sim.fields.registry import make_field
    from sim.flight import fly
    from sim.scene import build_scene
    from sim.wind import DrydenWind

    leader = np.array(LEADER_POSITION)
    reference = stack([Hover(leader, n_worlds=2), Transect(leader - [0, 0, 0.6], x_offset=[0.0, 0.1], n_worlds=2)])
    truth = make_field(field)
    if oracle:  # (a field with memory is known to its oracle only as the same object)
        from sim.predictor import OraclePredictor

        predictor = OraclePredictor(truth)
    components: dict[str, Any] = {"field": truth, "predictor": predictor}
    if wind:
        components["wind"] = DrydenWind(mean=(2.0, 0.0, 0.0))
    fly(build_scene(), reference, [0, 1], 0.1, **components)


def _learned(kind: str, guarded: bool) -> Any:
    """An untrained model of `kind` in the predictor slot (behind the guard when asked)."""
    import torch

    from downwash.checkpoint import Checkpoint
    from downwash.datasets import aggregation_record
    from downwash.guard import GuardedPredictor
    from downwash.predictor import LearnedPredictor
    from downwash.registry import SET_KINDS, make_model
    from downwash.support import support_of
    from sim.neighbours import NeighbourSet

    torch.manual_seed(0)
    model = make_model(kind).eval()
    if kind in SET_KINDS:  # a model of sets comes with the neighbour set it was made for
        model = Checkpoint(model, {"neighbours": NeighbourSet(3).describe(), "aggregation": aggregation_record("linear")})
    predictor = LearnedPredictor(model)
    if not guarded:
        return predictor
    rng = np.random.default_rng(0)
    dp = rng.normal(size=(64, 3)) * 0.2 + [0.0, 0.0, -0.6]  # the target below its neighbour
    v = rng.normal(size=(64, 3)) * 0.3
    support = support_of(dp, v, v, np.broadcast_to(np.eye(3), (64, 3, 3)))
    return GuardedPredictor(predictor, support=support)


def _envs(quick: bool) -> None:
    import gymnasium as gym

    import downwash_envs  # noqa: F401  (registers the ids)

    env = gym.make("downwash/Follower-v2")
    env.reset(seed=0)
    env.step(np.zeros(3, np.float32))
    env.close()
    if quick:
        return
    vec = gym.make_vec("downwash/Follower-v2", num_envs=2)
    vec.reset(seed=0)
    vec.step(np.zeros((2, 3), np.float32))
    vec.close()
    try:
        from downwash_envs.swarm import parallel_env
    except ImportError:  # the multiagent extra is not installed: nobody flies the swarm env
        return
    swarm = parallel_env()
    swarm.reset(seed=0)
    swarm.step({a: np.zeros(3, np.float32) for a in swarm.agents})
    swarm.close()


def workloads(quick: bool) -> list[tuple[str, Callable[[], None]]]:
    """(label, call) of everything to compile; --quick: the lemniscate experiment's and the env's."""
    jobs: list[tuple[str, Callable[[], None]]] = [
        ("pair flight, no model", lambda: _pair_flight()),
        ("pair flight, the true field", lambda: _pair_flight(oracle=True)),
    ]
    kinds = ("equivariant",) if quick else MODEL_KINDS
    for kind in kinds:
        for guarded in (False, True):
            label = f"pair flight, {kind}{' guarded' if guarded else ''}"
            jobs.append((label, lambda k=kind, g=guarded: _pair_flight(predictor=_learned(k, g))))
    if not quick:
        for field in FIELDS[1:]:
            jobs.append((f"pair flight, {field} field", lambda f=field: _pair_flight(f, oracle=True)))
        jobs.append(("pair flight in wind", lambda: _pair_flight(wind=True)))
    jobs.append(("envs", lambda: _envs(quick)))
    return jobs


def main(argv: Sequence[str] | None = None) -> dict[str, float]:
    """Fly every workload; returns label -> seconds."""
    args = build_parser().parse_args(argv)
    from downwash_core.jit import first_use_marker

    seconds: dict[str, float] = {}
    start = time.perf_counter()
    for label, call in workloads(args.quick):
        t = time.perf_counter()
        call()
        seconds[label] = time.perf_counter() - t
        print(f"{label}: {seconds[label]:.1f} s", flush=True)
    print(f"compiled and cached in {time.perf_counter() - start:.1f} s ({first_use_marker().parent})")
    return seconds


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
