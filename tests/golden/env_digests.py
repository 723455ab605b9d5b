"""Record the env digests that `tests/test_env.py` compares against, bit for bit.

    python tests/golden/env_digests.py            # writes tests/golden/env_digests.json
    python tests/golden/env_digests.py --print    # prints this machine's digests as JSON

Each case: reset(seed=7), 50 steps of uniform random actions from default_rng(1); the
single env resets when an episode ends, the vector env autoresets (3 worlds). The
digest covers observations, rewards, flags and infos. No learned model flies in these
envs, so the digests are the same on every CPU (`downwash_core.numerics`): the test
holds them exactly, and runs them again under every OpenBLAS kernel the CPU can run.
Re-record only with a change that is meant to move numbers, and say so in its commit.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path

import numpy as np

_spec = importlib.util.spec_from_file_location("golden_machine", Path(__file__).parent / "machine.py")
machine = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(machine)

GOLDEN = Path(__file__).resolve().parent / "env_digests.json"

CASES = {  # name: (env id, options, vector)
    "lemniscate": ("downwash/Follower-v2", {}, False),
    "passes": ("downwash/FollowerPasses-v2", {}, False),
    "acceleration_hover_randomised": ("downwash/Follower-v2", dict(
        action_mode="acceleration", reference="hover", separation=(0.4, 0.8), max_tracking_error=0.5,
        field_randomization="default", mass_randomization=(0.8, 1.2)), False),
    "vector_transect_oracle_25hz": ("downwash/Follower-v2", dict(
        reference="transect", predictor="oracle", control_hz=25, max_episode_steps=20), True),
}


def digest(name: str, steps: int = 50) -> str:
    import gymnasium as gym

    import downwash_envs  # noqa: F401  (registers the ids)

    env_id, opts, vector = CASES[name]

    def add_info(info):
        for k in sorted(info):
            h.update(k.encode())
            h.update(np.asarray(info[k]).astype(np.float64).tobytes())

    h = hashlib.sha256()
    rng = np.random.default_rng(1)
    if vector:
        env = gym.make_vec(env_id, num_envs=3, vectorization_mode="vector_entry_point", **opts)
        high, shape = env.single_action_space.high, (3, 3)
    else:
        env = gym.make(env_id, **opts)
        high, shape = env.action_space.high, (3,)
    obs, info = env.reset(seed=7)
    h.update(obs.tobytes())
    add_info(info)
    for _ in range(steps):
        obs, reward, term, trunc, info = env.step(rng.uniform(-high, high, shape).astype(np.float32))
        h.update(obs.tobytes())
        h.update(np.asarray([reward], np.float64).tobytes())
        h.update(np.asarray([term, trunc], bool).tobytes())
        add_info(info)
        if not vector and (term or trunc):
            obs, info = env.reset()
            h.update(obs.tobytes())
            add_info(info)
    env.close()
    return h.hexdigest()


def digests() -> dict[str, str]:
    return {name: digest(name) for name in sorted(CASES)}


def main() -> None:
    if "--print" in sys.argv:
        print(json.dumps(digests()))
        return
    GOLDEN.write_text(json.dumps({"machine": machine.machine(), "digests": digests()}, indent=1, sort_keys=True) + "\n")
    print(f"wrote {GOLDEN}")


if __name__ == "__main__":
    main()
