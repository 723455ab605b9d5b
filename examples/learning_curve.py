"""What the examples share: record each finished episode's return during training, and
plot and save the learning curve (`learning_curve.png`, `learning_curve.json`)."""

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


def save(out: Path, title: str, curve: EpisodeReturns, extra: dict) -> dict:
    """Write the curve (JSON and PNG) into `out`; returns the JSON record."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out.mkdir(parents=True, exist_ok=True)
    steps = np.array([e[0] for e in curve.episodes], dtype=float)
    returns = np.array([e[1] for e in curve.episodes], dtype=float)
    record = {"title": title, "wall_seconds": time.perf_counter() - curve.start,
              "episodes": [{"timestep": s, "return": r, "length": n} for s, r, n in curve.episodes], **extra}
    (out / "learning_curve.json").write_text(json.dumps(record, indent=1) + "\n")
    fig, ax = plt.subplots(figsize=(6, 3.5))
    if len(returns):
        ax.plot(steps, returns, ".", alpha=0.3, label="episode")
        k = max(1, len(returns) // 20)
        smooth = np.convolve(returns, np.ones(k) / k, mode="valid")
        ax.plot(steps[k - 1:], smooth, label=f"mean of {k}")
    ax.set(xlabel="environment steps", ylabel="episode return", title=title)
    ax.legend(loc="lower right")
    fig.tight_layout()
    fig.savefig(out / "learning_curve.png", dpi=100)
    plt.close(fig)
    if len(returns):
        first, last = returns[: max(1, len(returns) // 10)].mean(), returns[-max(1, len(returns) // 10):].mean()
        print(f"{title}: {len(returns)} episodes, mean return of the first tenth {first:.1f}, of the last {last:.1f}")
    print(f"wrote {out / 'learning_curve.png'} and {out / 'learning_curve.json'}")
    return record
