"""Multi-agent: one shared PPO policy (stable-baselines3) for every follower of a vehicle
stack, each agent of each world a row of an SB3 vector env.

    python examples/ppo_swarm.py                     # 200k agent steps on the stack3 preset
    python examples/ppo_swarm.py --quick             # a smoke run
    python examples/ppo_swarm.py --vec supersuit     # the same through SuperSuit
    python examples/ppo_swarm.py --load runs/examples/ppo_swarm/policy.zip   # evaluate it

`--vec native` (the default) steps every world in one batched simulator through the adapter
`downwash_envs.swarm_sb3`; `--vec supersuit` builds the same rows from copies of the
ParallelEnv with SuperSuit, one simulator each, stepped one after the other (slower; the
rows, their order and, for the same seed, their numbers are the same).

The agents are named by role (follower_0, follower_1, ...), so the same env also groups
them as one team in TorchRL or BenchMARL. Writes `learning_curve.png` and
`learning_curve.json` into --out, and the shared policy to --save (default
`<--out>/policy.zip`, an SB3 zip: `PPO.load(path)`). `--load PATH` skips training and
evaluates that policy on every follower against the plain LQR (mean return and its spread);
give it the --preset it was trained on.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from policy_file import add_policy_arguments, add_tensorboard_arguments, refuse_missing, tensorboard_dir


def main(argv: list[str] | None = None) -> dict:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--timesteps", type=int, default=200_000, help="agent steps to train (default 200000)")
    p.add_argument("--preset", default="stack3", help="the vehicle stack (default stack3: a leader, two followers)")
    p.add_argument("--copies", type=int, default=4, help="worlds (copies of the env) stepped together (default 4)")
    p.add_argument("--vec", choices=("native", "supersuit"), default="native",
                   help="the vector env: native (one batched simulator, the default) or supersuit")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", type=Path, default=Path("runs/examples/ppo_swarm"))
    p.add_argument("--quick", action="store_true", help="a tiny budget, for smoke tests")
    add_policy_arguments(p)
    add_tensorboard_arguments(p)
    args = p.parse_args(argv)
    if args.timesteps <= 0 or args.copies <= 0:
        p.error(f"--timesteps and --copies: expected positive numbers, got {args.timesteps}, {args.copies}")
    refuse_missing(p.prog, args.load)

    import torch

    from stable_baselines3 import PPO
    from stable_baselines3.common.utils import set_random_seed
    from stable_baselines3.common.vec_env import VecMonitor

    from downwash_envs.swarm import parallel_env
    from learning_curve import EpisodeReturns, against_the_lqr, save, swarm_returns
    from policy_file import evaluation, load_policy, save_policy

    copies = 1 if args.quick else args.copies
    # A 64-unit MLP policy gains nothing from a second torch thread, and on a small machine
    # torch's threads take the cores the simulator's threads step the worlds on.
    torch.set_num_threads(1)
    timesteps = 256 if args.quick else args.timesteps
    options = dict(preset=args.preset, duration=1.0 if args.quick else 5.0)
    if args.vec == "native":
        from downwash_envs.swarm_sb3 import make_vec_env

        venv = make_vec_env(copies, seed=args.seed, **options)  # one row per agent per world; world w: seed + w
        agents = venv.agents
    else:
        import supersuit as ss

        env = parallel_env(**options)
        env.reset(seed=args.seed)  # later resets (SuperSuit's, unseeded) continue this generator
        venv = ss.pettingzoo_env_to_vec_env_v1(env)  # one row per agent: the policy is shared
        venv = ss.concat_vec_envs_v1(venv, copies, num_cpus=0, base_class="stable_baselines3")
        agents = list(env.possible_agents)
    venv = VecMonitor(venv)
    # the envs are seeded above (SuperSuit's vector env has no seed()): seed the libraries here, not
    # through PPO(seed=...), so that both --vec choices train from the same initial policy
    set_random_seed(args.seed)
    episodes = 2 if args.quick else 10
    if args.load is not None:
        model = load_policy(p.prog, PPO, args.load, venv)
        lines = against_the_lqr(swarm_returns, model, episodes, **options)
        return evaluation(args.load, f"PPO, shared policy, {args.preset}", lines)
    model = PPO("MlpPolicy", venv, n_steps=64 if args.quick else 512, batch_size=64 if args.quick else 256,
                device="cpu", verbose=0, tensorboard_log=tensorboard_dir(p.prog, args))
    curve = EpisodeReturns()
    model.learn(timesteps, callback=curve)
    save_policy(model, args.save or args.out / "policy.zip")
    lines = against_the_lqr(swarm_returns, model, episodes, **options)
    return save(args.out, f"PPO, shared policy, {args.preset}", curve,
                {"timesteps": timesteps, "agents": agents, "copies": copies, "vec": args.vec, "seed": args.seed}, lines)


if __name__ == "__main__":
    main()
