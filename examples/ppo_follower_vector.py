"""PPO (stable-baselines3) on the native batched follower env through the SB3 adapter:
every world steps in one MuJoCo batch with compiled control.

    python examples/ppo_follower_vector.py           # 300k steps on 16 worlds
    python examples/ppo_follower_vector.py --quick   # a smoke run
    python examples/ppo_follower_vector.py --load runs/examples/ppo_follower_vector/policy.zip

Writes `learning_curve.png` and `learning_curve.json` into --out, SB3's TensorBoard logs into
--tensorboard (default `<--out>/tensorboard`, one PPO_<n> folder per run), and the trained
policy to --save (default `<--out>/policy.zip`, an SB3 zip: `PPO.load(path)`). `--load PATH`
skips training and evaluates that policy against the plain LQR (mean return and its spread).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from policy_file import add_policy_arguments, add_tensorboard_arguments, refuse_missing


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=300_000, help="environment steps to train (default 300000)")
    p.add_argument("--num-envs", type=int, default=16, help="worlds stepped together (default 16)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/examples/ppo_follower_vector"))
    p.add_argument("--quick", action="store_true", help="a tiny budget, for smoke tests")
    add_policy_arguments(p)
    add_tensorboard_arguments(p)
    args = p.parse_args(argv)
    if args.timesteps <= 0 or args.num_envs <= 0:
        p.error(f"--timesteps and --num-envs: expected positive numbers, got {args.timesteps}, {args.num_envs}")
    refuse_missing(p.prog, args.load)

    import torch

    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import VecMonitor

    from downwash_envs.sb3 import make_vec_env
    from learning_curve import EpisodeReturns, against_the_lqr, follower_returns, save
    from policy_file import evaluation, load_policy, save_policy, tensorboard_dir

    n = 4 if args.quick else args.num_envs
    # A 64-unit MLP policy gains nothing from a second torch thread, and on a small machine
    # torch's threads take the cores the simulator's threads step the worlds on.
    torch.set_num_threads(1)
    timesteps = 256 if args.quick else args.timesteps
    max_steps = 50 if args.quick else 250
    venv = VecMonitor(make_vec_env("downwash/Follower-v2", num_envs=n, seed=args.seed, max_episode_steps=max_steps))
    episodes = 2 if args.quick else 10
    if args.load is not None:
        model = load_policy(p.prog, PPO, args.load, venv)
        lines = against_the_lqr(follower_returns, model, episodes, max_episode_steps=max_steps)
        return evaluation(args.load, "PPO, native vector env", lines)
    model = PPO("MlpPolicy", venv, n_steps=32 if args.quick else 256, batch_size=64 if args.quick else 512,
                seed=args.seed, device="cpu", verbose=0, tensorboard_log=tensorboard_dir(p.prog, args))
    curve = EpisodeReturns()
    model.learn(timesteps, callback=curve)
    save_policy(model, args.save or args.out / "policy.zip")
    lines = against_the_lqr(follower_returns, model, episodes, max_episode_steps=max_steps)
    return save(args.out, f"PPO, native vector env ({n} worlds)", curve,
                {"timesteps": timesteps, "num_envs": n, "seed": args.seed}, lines)


if __name__ == "__main__":
    main()
