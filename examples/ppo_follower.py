"""PPO (stable-baselines3) on the single follower env: learn a residual on top of the LQR
that compensates the leader's downwash.

    python examples/ppo_follower.py                  # 100k steps, a few minutes on 2 cores
    python examples/ppo_follower.py --quick          # a smoke run
    python examples/ppo_follower.py --load runs/examples/ppo_follower/policy.zip   # evaluate it

Writes `learning_curve.png` and `learning_curve.json` into --out, SB3's TensorBoard logs into
--tensorboard (default `<--out>/tensorboard`, one PPO_<n> folder per run), and the trained
policy to --save (default `<--out>/policy.zip`, an SB3 zip: `PPO.load(path)`). `--load PATH`
skips training and evaluates that policy against the plain LQR (mean return and its spread). The
same task on the native batched env, several times faster: examples/ppo_follower_vector.py.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from policy_file import add_policy_arguments, add_tensorboard_arguments, refuse_missing


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=100_000, help="environment steps to train (default 100000)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/examples/ppo_follower"))
    p.add_argument("--quick", action="store_true", help="a tiny budget, for smoke tests")
    add_policy_arguments(p)
    add_tensorboard_arguments(p)
    args = p.parse_args(argv)
    if args.timesteps <= 0:
        p.error(f"--timesteps: expected a positive number of steps, got {args.timesteps}")
    refuse_missing(p.prog, args.load)

    import torch

    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.monitor import Monitor

    import downwash_envs  # noqa: F401  (registers the ids)
    from learning_curve import EpisodeReturns, against_the_lqr, follower_returns, save
    from policy_file import evaluation, load_policy, save_policy, tensorboard_dir

    # A 64-unit MLP policy gains nothing from a second torch thread, and on a small machine
    # torch's threads take the cores the simulator's threads step the worlds on.
    torch.set_num_threads(1)
    timesteps = 256 if args.quick else args.timesteps
    max_steps = 50 if args.quick else 250  # 5 s episodes: several per PPO rollout
    env = Monitor(gym.make("downwash/Follower-v2", max_episode_steps=max_steps))
    episodes = 2 if args.quick else 10
    if args.load is not None:
        model = load_policy(p.prog, PPO, args.load, env)
        lines = against_the_lqr(follower_returns, model, episodes, max_episode_steps=max_steps)
        return evaluation(args.load, "PPO, single env", lines)
    model = PPO("MlpPolicy", env, n_steps=128 if args.quick else 2048, batch_size=64, seed=args.seed,
                device="cpu", verbose=0, tensorboard_log=tensorboard_dir(p.prog, args))
    curve = EpisodeReturns()
    model.learn(timesteps, callback=curve)
    save_policy(model, args.save or args.out / "policy.zip")
    lines = against_the_lqr(follower_returns, model, episodes, max_episode_steps=max_steps)
    return save(args.out, "PPO, single env", curve, {"timesteps": timesteps, "num_envs": 1, "seed": args.seed}, lines)


if __name__ == "__main__":
    main()
