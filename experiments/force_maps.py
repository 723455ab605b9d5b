"""Force maps like the paper's figures 4 and 5: the true field beside each trained model.

    python -m experiments.force_maps [--models-dir DIR] [--quick]

Figure 4 (force_maps_down.png): the downward force (m/s^2, positive pushes toward
the ground, the paper's +e3) on a follower moving at v = [0.5, 0, 0] m/s, top-down
with the follower 1 m below the leader, and sagittal (x-z) 0.1 m beside it.
Figure 5 (force_maps_lateral.png): lateral-force quivers 0.8 m below the leader for
v = +0.5 and -0.5 m/s along x. Rows: truth, then each model found in --models-dir
(missing models are run through the staged collection first).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np

from downwash_core.errors import ConfigError
from experiments.common import (PipelineArgs, ProgressBar, arg, format_table, out_lock, parse_args, resolve_pipeline,
                                run_main, setup_logging, write_results, script)

__all__ = ["ForceMapArgs", "run", "main"]


@dataclass(frozen=True)
class ForceMapArgs(PipelineArgs):
    speed: float = arg(0.5, "follower speed along x, m/s (paper: 0.5)", ge=0.0, le=1.0)
    resolution: int = arg(61, "grid points per axis", ge=5, le=301)


def _evaluate(fn: Any, dp: np.ndarray, v_b: np.ndarray) -> np.ndarray:
    """Force (N, 3) m/s^2 on followers at dp (N, 3) below a level leader at rest."""
    n = dp.shape[0]
    return fn(np.zeros((n, 3)), np.zeros((n, 3)), np.broadcast_to(np.eye(3), (n, 3, 3)), dp, v_b)


def _model_fn(model: Any):
    from downwash.train import predict

    def fn(p_a, v_a, R_a, p_b, v_b):
        data = SimpleNamespace(dp=p_b - p_a, v_a=v_a, v_b=v_b, R_a=np.ascontiguousarray(R_a))
        return predict(model, data)

    return fn


def run(args: ForceMapArgs) -> dict:
    import matplotlib

    from downwash.checkpoint import load_checkpoint
    from downwash.models import STAGED_KINDS
    from downwash.staged import ensure_models

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    if not 0 <= args.speed <= 1.0:
        raise ConfigError(f"--speed: allowed 0-1.0 m/s, got {args.speed}")
    if not 5 <= args.resolution <= 301:
        raise ConfigError(f"--resolution: allowed 5-301, got {args.resolution}")
    p = resolve_pipeline(args)
    field = p.field
    checkpoints = ensure_models(p.models_dir, STAGED_KINDS, p.collection_dir, p.config, field, ProgressBar)
    sources = {"truth": field}
    for kind, path in checkpoints.items():
        model, _ = load_checkpoint(path, expect_kind=kind)
        sources[kind] = _model_fn(model)

    n = 21 if args.quick else args.resolution
    g = np.linspace(-1.0, 1.0, n)
    X, Y = np.meshgrid(g, g)
    top = np.stack([X.ravel(), Y.ravel(), np.full(X.size, -1.0)], axis=1)  # 1 m below
    zs = np.linspace(-1.8, -0.2, n)
    XS, ZS = np.meshgrid(g, zs)
    side = np.stack([XS.ravel(), np.full(XS.size, 0.1), ZS.ravel()], axis=1)  # 0.1 m beside
    v = np.tile([args.speed, 0.0, 0.0], (X.size, 1))

    results: dict[str, Any] = {"speed": args.speed, "maps": {}}
    fig, axes = plt.subplots(len(sources), 2, figsize=(9, 3.2 * len(sources)), squeeze=False)
    truth_top = None
    for row, (name, fn) in enumerate(sources.items()):
        down_top = -_evaluate(fn, top, v)[:, 2].reshape(n, n)
        down_side = -_evaluate(fn, side, v)[:, 2].reshape(n, n)
        if truth_top is None:
            truth_top, truth_side = down_top, down_side
            results["truth"] = {"down_top_max": float(np.abs(down_top).max()),
                                "down_side_max": float(np.abs(down_side).max())}
        else:
            results["maps"][name] = {
                "down_top_rmse_vs_truth": float(np.sqrt(np.mean((down_top - truth_top) ** 2))),
                "down_side_rmse_vs_truth": float(np.sqrt(np.mean((down_side - truth_side) ** 2))),
            }
        lim = max(np.abs(truth_top).max(), np.abs(truth_side).max(), 1e-6)  # a zero field still plots
        for ax, data, extent, labels in (
            (axes[row, 0], down_top, (-1, 1, -1, 1), ("x (m)", "y (m)")),
            (axes[row, 1], down_side, (-1, 1, -1.8, -0.2), ("x (m)", "z below leader (m)")),
        ):
            im = ax.imshow(data, origin="lower", extent=extent, cmap="RdBu_r", vmin=-lim, vmax=lim, aspect="auto")
            ax.plot(0, 0 if ax is axes[row, 0] else -0.2, "k^")
            ax.set_xlabel(labels[0]), ax.set_ylabel(labels[1])
        axes[row, 0].set_title(f"{name}: top-down, 1 m below", fontsize=9)
        axes[row, 1].set_title(f"{name}: sagittal, 0.1 m beside", fontsize=9)
        fig.colorbar(im, ax=axes[row].tolist(), label="downward force (m/s^2)")
    fig.suptitle(f"downward force, follower moving at v = [{args.speed}, 0, 0] m/s")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "force_maps_down.png", dpi=100)
    plt.close(fig)

    # figure 5: lateral quivers 0.8 m below, for +v and -v
    nq = 11 if args.quick else 17
    gq = np.linspace(-1.0, 1.0, nq)
    QX, QY = np.meshgrid(gq, gq)
    plane = np.stack([QX.ravel(), QY.ravel(), np.full(QX.size, -0.8)], axis=1)
    fig, axes = plt.subplots(len(sources), 2, figsize=(8, 3.8 * len(sources)), squeeze=False)
    truth_lat = {}
    for row, (name, fn) in enumerate(sources.items()):
        for col, sign in enumerate((1.0, -1.0)):
            f = _evaluate(fn, plane, np.tile([sign * args.speed, 0.0, 0.0], (plane.shape[0], 1)))
            ax = axes[row, col]
            ax.quiver(plane[:, 0], plane[:, 1], f[:, 0], f[:, 1], np.hypot(f[:, 0], f[:, 1]), cmap="viridis")
            ax.plot(0, 0, "k^"), ax.set_aspect("equal")
            ax.set_title(f"{name}: v = {sign * args.speed:+.1f} m/s along x", fontsize=9)
            if name == "truth":
                truth_lat[sign] = f[:, :2]
            else:
                results["maps"][name][f"lateral_rmse_vs_truth_{'pos' if sign > 0 else 'neg'}"] = float(
                    np.sqrt(np.mean((f[:, :2] - truth_lat[sign]) ** 2)))
    fig.suptitle("lateral force 0.8 m below the leader")
    fig.tight_layout()
    fig.savefig(out / "force_maps_lateral.png", dpi=100)
    plt.close(fig)

    path = write_results(out, results, args, p.provenance())
    rows = [[m, r["down_top_rmse_vs_truth"], r["down_side_rmse_vs_truth"], r["lateral_rmse_vs_truth_pos"],
             r["lateral_rmse_vs_truth_neg"]] for m, r in results["maps"].items()]
    print(format_table(rows, ["model", "down top RMSE", "down side RMSE", "lateral +v RMSE", "lateral -v RMSE"]))
    print(f"\nwrote {path}, force_maps_down.png and force_maps_lateral.png in {out}/")
    return results


def main(argv=None) -> dict:
    setup_logging()
    args = parse_args(ForceMapArgs, "force_maps", argv, __doc__)
    with out_lock(args, "force_maps"):
        return run(args)


cli = script(main)  # the console script (pyproject.toml)


if __name__ == "__main__":
    run_main(main)
