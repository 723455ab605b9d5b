"""The speed section of the results page: what users want first (real time, env steps, MuJoCo's own
stepping), then the benchmark's full record with the project's aims."""

from __future__ import annotations

from experiments.report.formatting import markdown_table, fmt

__all__ = ["render_benchmark"]


def _speed_summary(r: dict) -> list[list[str]]:
    """What a user wants first: flights against real time, env steps, MuJoCo's own batched stepping, and
    each scene's batched flights against MuJoCo's rollout of it."""
    worlds, rows = r.get("batched_worlds"), []

    def add(what: str, key: str, note: str = "", sig: int = 3) -> None:
        if r.get(key) is not None:
            rows.append([what, fmt(r[key], sig), note])

    add("one flight (two vehicles, 500 Hz physics, the full stack), times real time", "real_time_factor_serial",
        "" if r.get("serial_over_bare_no_timer") is None else
        f"{fmt(r.get('serial_over_bare'), 3)}x one bare `mj_step` loop, {fmt(r['serial_over_bare_no_timer'], 3)}x "
        "one without MuJoCo's profiling timer (the simulator steps without it)")
    add(f"{worlds} worlds in one batch, world-steps/s", "closed_loop_batched_world_steps_per_s",
        f"{fmt(r.get('batched_over_bare'), 3)}x one bare `mj_step` loop")
    add(f"MuJoCo's own batched stepping (`mujoco.batch`), {worlds} worlds, no control at all, world-steps/s",
        "mujoco_batch_world_steps_per_s", f"{fmt(r.get('mujoco_batch_over_bare'), 3)}x one bare `mj_step` loop")
    # each scene's batched flights against MuJoCo's rollout of that scene (older files have none)
    for what, ours, prefix, ratio in (
            (f"the pair, {worlds} worlds", "closed_loop_batched_world_steps_per_s", "", "batched_over_mujoco_rollout"),
            (f"`formation5` (five vehicles), {worlds} worlds", "formation5_batched_world_steps_per_s", "formation5_",
             "formation5_batched_over_mujoco_rollout"),
            (f"the swarm env as a `VecEnv` ({r.get('swarm_preset')}, {r.get('swarm_worlds')} worlds)",
             "swarm_world_steps_per_s_native", "swarm_", "swarm_native_over_mujoco_rollout")):
        if r.get(ratio) is not None:
            no_timer = r.get(ratio + "_no_timer")  # (older files have none)
            add(f"{what} in one batch against MuJoCo's own rollout of the same scene (`mujoco.rollout`, no control), "
                "world-steps/s", ours, f"{fmt(r[ratio], 3)}x of MuJoCo's rollout "
                f"({fmt(r.get(prefix + 'mujoco_rollout_world_steps_per_s'))} world-steps/s)"
                + ("" if no_timer is None else f"; {fmt(no_timer, 3)}x of it with its profiling timer off too"))
    add("the single env (`gym.make`), steps/s", "env_steps_per_s_single", "an env step is 0.02 s of flight")
    add(f"the native vector env, {worlds} worlds, steps/s", "env_steps_per_s_vector64_solo")
    add(f"stable-baselines3 PPO's rollout through the native vector env, {r.get('sb3_worlds')} worlds, steps/s",
        "sb3_rollout_steps_per_s_native", f"{fmt(r.get('sb3_native_over_sync'), 3)}x through Gymnasium's `SyncVectorEnv`")
    add(f"the swarm env as a stable-baselines3 `VecEnv` ({r.get('swarm_preset')}, {r.get('swarm_worlds')} worlds), "
        "agent-steps/s", "swarm_agent_steps_per_s_native",
        f"{fmt(r.get('swarm_native_over_supersuit'), 3)}x SuperSuit's vectorised env")
    add("training the equivariant model on the staged collection's data, s", "train_seconds_equivariant_full")
    return rows


def _interval(lo_hi: list[float] | None) -> str:
    return "-" if not lo_hi else f"{fmt(lo_hi[0], 3)} to {fmt(lo_hi[1], 3)}"


def render_benchmark(r: dict, label: str) -> str:
    parts = [f"Measured by `python -m experiments.benchmark` on {r.get('cpu_count')} cores (mujoco {r.get('mujoco')}), "
             "every rate from one run:", markdown_table(["", "measured", ""], _speed_summary(r)),
             "### The benchmark's full record"]
    targets = r.get("targets") or {}
    if targets:
        intervals = r.get("ratio_intervals") or {}
        rows = [[f"`{k}`", f">= {v:g}", fmt(r.get(k), 3), _interval(intervals.get(k)),
                 "yes" if (r.get(k) or 0.0) >= v else "no"] for k, v in targets.items()]
        parts += [f"The ratios the project aims for, as measured in this run ({r.get('rounds')} rounds, each "
                  "simulation ratio the median over rounds of the rate over a bare `mj_step` window just before it, "
                  "or for a ratio of two of our flights, of the one's rate over the other's flown right beside it; "
                  "the `sb3_*` ratios: stable-baselines3's rollout collection through the native vector env over "
                  f"the same through the other vector env, {r.get('sb3_worlds')} worlds, torch at "
                  f"{r.get('sb3_torch_threads')} thread(s), the median of alternated rounds). The interval is "
                  "the run's own uncertainty: a distribution-free 95 % interval of the median over its rounds, "
                  "where the rounds allow one. Runs "
                  "of the same code minutes apart have moved further than it "
                  "([design notes](design-notes.md#the-benchmarks-spread)):",
                  markdown_table(["ratio", "aim", "measured", "95 % interval", "reached"], rows)]
    rows = [[f"`{k}`", fmt(v, 4)] for k, v in sorted(r.items()) if isinstance(v, float)]
    parts += [f"Every rate and ratio, {r.get('batched_worlds')} batched worlds (`{label}`):", markdown_table(["key", "value"], rows)]
    return "\n\n".join(parts)
