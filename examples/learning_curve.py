"""What the examples share: record each finished episode's return during training, measure
the trained policy and the plain LQR (action 0) on the same evaluation episodes, and plot
and save the learning curve with both as lines (`learning_curve.png`, `learning_curve.json`).
Writing and loading the trained policy is `policy_file.py`."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from stable_baselines3.common.callbacks import BaseCallback


class EpisodeReturns(BaseCallback):
    """Collects (timestep, return, length) of every episode that ends, from the `episode`
    entries that SB3's Monitor / VecMonitor put in the step infos."""

    def __init__(self):
        super().__init__()
        self.episodes: list[tuple[int, float, int]] = []
        self.start = time.perf_counter()

    def _on_step(self) -> bool:
        for info in self.locals.get("infos", []):
            ep = info.get("episode")
            if ep is not None:
                self.episodes.append((int(self.num_timesteps), float(ep["r"]), int(ep["l"])))
        return True


def follower_returns(policy, episodes: int = 10, seed: int = 1000, **options) -> list[float]:
    """Returns of `episodes` episodes of the single follower env (`options` as to gymnasium.make)
    flown by `policy` (obs -> normalised action; None: action 0, the plain LQR), seeds seed + k."""
    import gymnasium as gym

    import downwash_envs  # noqa: F401  (registers the ids)

    env = gym.make("downwash/Follower-v2", **options)
    out = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        total, done = 0.0, False
        while not done:
            action = np.zeros(3, np.float32) if policy is None else policy(obs)
            obs, reward, terminated, truncated, _ = env.step(action)
            total, done = total + reward, terminated or truncated
        out.append(total)
    env.close()
    return out


def swarm_returns(policy, episodes: int = 10, seed: int = 1000, **options) -> list[float]:
    """Per-agent returns (mean over the agents) of `episodes` episodes of the multi-agent env
    (`options` as to parallel_env) flown by `policy` (obs -> normalised action, shared by every
    agent; None: action 0, the plain LQR), seeds seed + k."""
    from downwash_envs.swarm import parallel_env

    env = parallel_env(**options)
    out = []
    for k in range(episodes):
        obs, _ = env.reset(seed=seed + k)
        totals = dict.fromkeys(env.possible_agents, 0.0)
        while env.agents:
            actions = {a: np.zeros(3, np.float32) if policy is None else policy(obs[a]) for a in env.agents}
            obs, rewards, *_ = env.step(actions)
            for a, r in rewards.items():
                totals[a] += float(r)
        out.append(float(np.mean(list(totals.values()))))
    env.close()
    return out


def against_the_lqr(returns, model, episodes: int, **options) -> dict[str, list[float]]:
    """The plain LQR (action 0) and `model` acting deterministically, on the same `episodes`
    evaluation episodes of `returns` (`follower_returns` or `swarm_returns`, with `options`)."""
    return {"LQR alone (action 0)": returns(None, episodes, **options),
            "PPO, deterministic": returns(lambda o: model.predict(o, deterministic=True)[0], episodes, **options)}


def save(out: Path, title: str, curve: EpisodeReturns, extra: dict,
         lines: dict[str, list[float]] | None = None) -> dict:
    """Write the curve (JSON and PNG) into `out`, with `lines` (label -> evaluation returns) drawn
    as their means; returns the JSON record."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    steps = np.array([e[0] for e in curve.episodes], dtype=float)
    returns = np.array([e[1] for e in curve.episodes], dtype=float)
    lines = lines or {}
    record = {"title": title, "wall_seconds": time.perf_counter() - curve.start,
              "evaluation": {label: {"mean": float(np.mean(v)), "returns": [float(x) for x in v]}
                             for label, v in lines.items()},
              "episodes": [{"timestep": s, "return": r, "length": n} for s, r, n in curve.episodes], **extra}
    (out / "learning_curve.json").write_text(json.dumps(record, indent=1) + "\n")
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if len(returns):
        ax.plot(steps, returns, ".", alpha=0.3, label="episode")
        k = max(1, len(returns) // 20)
        smooth = np.convolve(returns, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, label=f"mean of {k}")
    for (label, values), style in zip(lines.items(), ("--", ":", "-.")):
        ax.axhline(float(np.mean(values)), color="k", linestyle=style, linewidth=1,
                   label=f"{label}: {np.mean(values):.0f}")
    ax.set(xlabel="environment steps", ylabel="episode return", title=title)
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "learning_curve.png", dpi=100)
    plt.close(fig)
    if len(returns):
        first, last = returns[: max(1, len(returns) // 10)].mean(), returns[-max(1, len(returns) // 10):].mean()
        print(f"{title}: {len(returns)} episodes, mean return of the first tenth {first:.1f}, of the last {last:.1f}")
    for label, values in lines.items():
        print(f"  {label}: mean return {np.mean(values):.1f} over {len(values)} evaluation episodes")
    print(f"wrote {out / 'learning_curve.png'} and {out / 'learning_curve.json'}")
    return record
