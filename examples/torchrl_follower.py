"""PPO with TorchRL on the single follower env: learn a residual on top of the LQR
that compensates the leader's downwash, with TorchRL's own pieces end to end.

    python examples/torchrl_follower.py              # 100k frames, several minutes on 2 cores
    python examples/torchrl_follower.py --quick      # a smoke run
    python examples/torchrl_follower.py --load runs/examples/torchrl_follower/policy.pt   # evaluate it

TorchRL builds the env from its registered id (`torchrl.envs.GymEnv`), collects frames with its
collector, and trains a tanh-normal actor and a value MLP (`torchrl.modules`) with `ClipPPOLoss`
and `GAE`. Writes `learning_curve.png` and `learning_curve.json` into --out, TensorBoard logs
into --tensorboard (default `<--out>/tensorboard`), and the trained policy to --save (default
`<--out>/policy.pt`: the networks' weights and sizes, `torch.load(path, weights_only=True)`).
`--load PATH` skips training and evaluates that policy against the plain LQR on the same
seeded episodes (mean return, its spread, mean position error). The SB3 version of the same
task: examples/ppo_follower.py.
"""

from __future__ import annotations

import argparse
import time
from collections import deque
from pathlib import Path
from types import SimpleNamespace

from policy_file import add_policy_arguments, add_tensorboard_arguments, refuse_missing

ENV_ID = "downwash/Follower-v2"
POLICY_FORMAT = "downwash torchrl_follower PPO policy, v1"  # a --load file must say this
HIDDEN = (64, 64)  # SB3's default MlpPolicy, so the two examples compare like for like
LQR, PPO_LINE = "LQR alone (action 0)", "PPO, deterministic"


def make_env(max_steps: int, *, training: bool):
    """The env as TorchRL builds it from the id, reading each step's `position_error` (m) from the
    info; for training it also sums each episode's reward, counts its steps and marks its first
    step (InitTracker: TorchRL's collector asks for it before it would add it itself)."""
    import numpy as np
    import torch
    from torchrl.data import Unbounded
    from torchrl.envs import (
        Compose, GymEnv, InitTracker, RewardSum, StepCounter, TransformedEnv, default_info_dict_reader,
    )

    class NumericInfoReader(default_info_dict_reader):
        """TorchRL's reader takes numpy values; the env's infos are Python floats."""

        def __call__(self, info_dict, tensordict):
            return super().__call__({k: np.asarray(info_dict[k]) for k in self.keys if k in info_dict}, tensordict)

    env = GymEnv(ENV_ID, max_episode_steps=max_steps)
    env.set_info_dict_reader(NumericInfoReader(["position_error"], spec=[Unbounded((), dtype=torch.float64)]))
    return TransformedEnv(env, Compose(RewardSum(), StepCounter(), InitTracker())) if training else env


def build_agent(observation_size: int, action_spec, hidden=HIDDEN):
    """A tanh-normal actor (its mean squashed into the action box) and a value MLP, both on the
    observation."""
    from tensordict.nn import NormalParamExtractor, TensorDictModule
    from torch import nn
    from torchrl.modules import MLP, ProbabilisticActor, TanhNormal, ValueOperator

    actor_net = nn.Sequential(
        MLP(in_features=observation_size, out_features=2 * action_spec.shape[-1], num_cells=list(hidden),
            activation_class=nn.Tanh),
        NormalParamExtractor(),  # (loc, scale), scale > 0
    )
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=["observation"], out_keys=["loc", "scale"]),
        spec=action_spec, in_keys=["loc", "scale"], distribution_class=TanhNormal,
        distribution_kwargs={"low": action_spec.space.low, "high": action_spec.space.high},
        return_log_prob=True,  # PPO's ratio needs the collecting policy's log-probability
    )
    value_net = MLP(in_features=observation_size, out_features=1, num_cells=list(hidden), activation_class=nn.Tanh)
    return actor, ValueOperator(value_net, in_keys=["observation"])


def save_agent(actor, value, observation_size: int, action_size: int, path: Path) -> Path:
    """Write the networks' weights and sizes to `path` atomically (a dict of tensors and plain
    values, so `torch.load(weights_only=True)` reads it)."""
    import torch

    from policy_file import write_atomically

    payload = {"format": POLICY_FORMAT, "env_id": ENV_ID, "observation_size": observation_size,
               "action_size": action_size, "hidden": list(HIDDEN),
               "actor": actor.state_dict(), "value": value.state_dict()}
    write_atomically(path, lambda tmp: torch.save(payload, tmp))
    print(f"wrote the policy to {path} (load it with --load {path})")
    return path


def load_agent(prog: str, path: Path, env):
    """The actor saved at `path`, or exit with one line naming `path` when it is no policy of this
    example for this env (not a torch file, another program's, other sizes)."""
    import pickle
    import zipfile

    import torch

    from policy_file import refuse_foreign, refuse_missing

    refuse_missing(prog, path)
    observation_size, action_size = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    try:
        try:
            payload = torch.load(path, map_location="cpu", weights_only=True)
        except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile) as e:
            if zipfile.is_zipfile(path) and "policy.pth" in zipfile.ZipFile(path).namelist():
                raise ValueError("an SB3 zip: evaluate it with ppo_follower.py --load") from e
            raise ValueError("not a torch.save file of tensors and plain values") from e
        if not isinstance(payload, dict) or payload.get("format") != POLICY_FORMAT:
            raise ValueError(f"no '{POLICY_FORMAT}' in the file")
        if (payload["observation_size"], payload["action_size"]) != (observation_size, action_size):
            raise ValueError(f"its observations and actions have sizes {payload['observation_size']}, "
                             f"{payload['action_size']}, this env's {observation_size}, {action_size}")
        actor, _ = build_agent(observation_size, env.action_spec, tuple(payload["hidden"]))
        actor.load_state_dict(payload["actor"])
        return actor
    except (ValueError, KeyError, TypeError, RuntimeError, OSError, EOFError, pickle.UnpicklingError,
            zipfile.BadZipFile) as e:
        refuse_foreign(prog, path, "PPO", e)


def flown(env, policy, episodes: int, max_steps: int, seed: int = 1000) -> tuple[list[float], list[float]]:
    """Each episode's return and mean position error (m) with `policy` flying `env`, on the
    episodes of seeds seed + k (those of learning_curve.follower_returns)."""
    import torch

    returns, errors = [], []
    with torch.no_grad():
        for k in range(episodes):
            start = env.reset(seed=seed + k)
            steps = env.rollout(max_steps, policy, auto_reset=False, tensordict=start, break_when_any_done=True)
            returns.append(float(steps["next", "reward"].sum()))
            errors.append(float(steps["next", "position_error"].mean()))
    return returns, errors


def against_the_lqr(actor, episodes: int, max_steps: int) -> tuple[dict[str, list[float]], dict[str, list[float]]]:
    """Returns and position errors of the plain LQR (action 0) and of `actor` acting
    deterministically (its mean action), on the same evaluation episodes."""
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    env = make_env(max_steps, training=False)
    zero = env.action_spec.zero()
    lqr = flown(env, lambda td: td.set("action", zero), episodes, max_steps)
    with set_exploration_type(ExplorationType.DETERMINISTIC):
        ppo = flown(env, actor, episodes, max_steps)
    env.close()
    return {LQR: lqr[0], PPO_LINE: ppo[0]}, {LQR: lqr[1], PPO_LINE: ppo[1]}


def next_run_folder(root: Path, prefix: str = "PPO") -> str:
    """`<prefix>_<n>`, n one above the highest in `root`: a rerun logs beside the earlier runs, as
    SB3's `tensorboard_log` does."""
    taken = [int(p.name.rsplit("_", 1)[1]) for p in root.glob(f"{prefix}_*") if p.name.rsplit("_", 1)[1].isdigit()]
    return f"{prefix}_{max(taken, default=0) + 1}"


def train(env, actor, value, timesteps: int, frames_per_batch: int, tensorboard: Path | None, seed: int):
    """PPO with SB3's default settings (10 epochs of minibatches of 64, clip 0.2, GAE 0.99/0.95,
    Adam 3e-4, gradient norm 0.5); returns each finished episode's (frame, return, length) and
    the TensorBoard run folder (None without one)."""
    import torch
    from torchrl.objectives import ClipPPOLoss
    from torchrl.objectives.value import GAE

    try:
        from torchrl.collectors import Collector
    except ImportError:  # TorchRL before 0.11 named the single-process collector SyncDataCollector
        from torchrl.collectors import SyncDataCollector as Collector

    env.set_seed(seed)
    collector = Collector(env, actor, frames_per_batch=frames_per_batch, total_frames=timesteps, device="cpu")
    advantage = GAE(gamma=0.99, lmbda=0.95, value_network=value)
    loss_module = ClipPPOLoss(actor, value, clip_epsilon=0.2, entropy_bonus=False, critic_coeff=0.5,
                              loss_critic_type="l2", normalize_advantage=True)
    optimizer = torch.optim.Adam(loss_module.parameters(), lr=3e-4)
    logger, run = None, None
    if tensorboard is not None:
        from torchrl.record.loggers import TensorboardLogger

        tensorboard.mkdir(parents=True, exist_ok=True)
        run = tensorboard / next_run_folder(tensorboard)
        logger = TensorboardLogger(exp_name=run.name, log_dir=str(tensorboard))
    episodes: list[tuple[int, float, int]] = []
    recent = deque(maxlen=100)  # SB3's rollout/ep_rew_mean is the mean of the last 100 episodes
    frames = 0
    for batch in collector:
        with torch.no_grad():
            advantage(batch)
        data = batch.reshape(-1)
        stats = []
        for _ in range(10):
            for index in torch.randperm(data.shape[0]).split(64):
                losses = loss_module(data[index])
                loss = losses["loss_objective"] + losses["loss_critic"]
                optimizer.zero_grad()
                loss.backward()
                torch.nn.utils.clip_grad_norm_(loss_module.parameters(), 0.5)
                optimizer.step()
                stats.append([float(losses[k].detach()) for k in ("loss_objective", "loss_critic",
                                                                  "clip_fraction", "kl_approx")])
        ended = data["next", "done"].reshape(-1).nonzero().flatten()
        for i in ended.tolist():
            episodes.append((frames + i + 1, float(data["next", "episode_reward"][i]),
                             int(data["next", "step_count"][i])))
            recent.append(episodes[-1])
        frames += data.shape[0]
        if logger is not None:
            means = torch.tensor(stats).mean(0).tolist()
            for tag, v in zip(("train/policy_gradient_loss", "train/value_loss", "train/clip_fraction",
                               "train/approx_kl"), means):
                logger.log_scalar(tag, v, step=frames)
            logger.log_scalar("rollout/position_error_mean", float(data["next", "position_error"].mean()), step=frames)
            if recent:
                logger.log_scalar("rollout/ep_rew_mean", sum(e[1] for e in recent) / len(recent), step=frames)
                logger.log_scalar("rollout/ep_len_mean", sum(e[2] for e in recent) / len(recent), step=frames)
    collector.shutdown()
    if logger is not None:
        logger.experiment.close()
    return episodes, run


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=100_000,
                   help="environment steps (TorchRL's frames) to train (default 100000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/examples/torchrl_follower"))
    p.add_argument("--quick", action="store_true", help="a tiny budget, for smoke tests")
    add_policy_arguments(p, file="policy.pt", kind="a torch file of the networks' weights")
    add_tensorboard_arguments(p)
    args = p.parse_args(argv)
    if args.timesteps <= 0:
        p.error(f"--timesteps: expected a positive number of steps, got {args.timesteps}")
    refuse_missing(p.prog, args.load)

    import torch

    import downwash_envs  # noqa: F401  (registers the ids)
    from learning_curve import save
    from policy_file import evaluation, tensorboard_dir

    # A 64-unit MLP gains nothing from a second torch thread, and on a small machine torch's
    # threads take the cores the simulator's threads step the worlds on.
    torch.set_num_threads(1)
    torch.manual_seed(args.seed)
    timesteps = 256 if args.quick else args.timesteps
    max_steps = 50 if args.quick else 250  # 5 s episodes: several per batch of frames
    episodes = 2 if args.quick else 10
    title = "PPO (TorchRL), single env"
    if args.load is not None:
        probe = make_env(max_steps, training=False)
        actor = load_agent(p.prog, args.load, probe)
        probe.close()
        returns, errors = against_the_lqr(actor, episodes, max_steps)
        return evaluation(args.load, title, returns, errors)

    tensorboard = tensorboard_dir(p.prog, args)
    start = time.perf_counter()
    env = make_env(max_steps, training=True)
    observation_size, action_size = env.observation_spec["observation"].shape[-1], env.action_spec.shape[-1]
    actor, value = build_agent(observation_size, env.action_spec)
    frames_per_batch = min(128 if args.quick else 2048, timesteps)
    timesteps = -(-timesteps // frames_per_batch) * frames_per_batch  # whole batches, as SB3's rollouts
    curve, run = train(env, actor, value, timesteps, frames_per_batch, tensorboard, args.seed)
    env.close()
    save_agent(actor, value, observation_size, action_size, args.save or args.out / "policy.pt")
    returns, errors = against_the_lqr(actor, episodes, max_steps)
    position_error = {label: sum(v) / len(v) for label, v in errors.items()}
    record = save(args.out, title, SimpleNamespace(episodes=curve, start=start),
                  {"timesteps": timesteps, "num_envs": 1, "seed": args.seed, "position_error": position_error},
                  returns)
    for label, v in position_error.items():
        print(f"  {label}: mean position error {v:.4f} m over {len(errors[label])} evaluation episodes")
    if run is not None:
        print(f"wrote TensorBoard logs to {run} (tensorboard --logdir {run.parent})")
    return record


if __name__ == "__main__":
    main()
