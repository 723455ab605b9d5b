"""Envs pickle as the call that made them: a copy (SuperSuit's, a subprocess's) is a working
env with the same options, not a copy of a simulator that cannot move."""

import pickle

import gymnasium as gym
import numpy as np
import pytest

import downwash_envs  # noqa: F401
from downwash_envs.follower import DownwashFollowerEnv, DownwashFollowerVectorEnv


def _rollout(env, seed, n=30):
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for _ in range(n):
        obs, reward, *_ = env.step(np.full(env.action_space.shape, 0.3, np.float32))
        out += [obs, np.asarray(reward)]
    return out


@pytest.mark.parametrize("make", [
    lambda: DownwashFollowerEnv(reference="hover", separation=0.6),
    lambda: DownwashFollowerVectorEnv(2, reference="hover", separation=0.6),
])
def test_a_pickled_follower_env_flies_as_a_fresh_one(make):
    env = make()
    env.reset(seed=3)
    env.step(np.zeros(env.action_space.shape, np.float32))  # mid-episode: the copy starts afresh
    copy = pickle.loads(pickle.dumps(env))
    assert copy is not env and type(copy) is type(env) and copy.config == env.config
    a, b = _rollout(make(), 5), _rollout(copy, 5)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert not np.array_equal(a[1], a[-2])  # the copy's flight moves


def test_a_pickled_swarm_env_flies_as_a_fresh_one():
    pytest.importorskip("pettingzoo")
    from downwash_envs.swarm import parallel_env

    env = parallel_env(preset="stack3", duration=0.5, field="so2")
    copy = pickle.loads(pickle.dumps(env))
    fresh = parallel_env(preset="stack3", duration=0.5, field="so2")
    ra, rb = [], []
    for e, out in ((fresh, ra), (copy, rb)):
        e.reset(seed=2)
        while e.agents:
            _, rewards, *_ = e.step({a: np.zeros(3, np.float32) for a in e.agents})
            out.append([rewards[a] for a in sorted(rewards)])
    assert ra == rb and len(ra) == 25
    assert max(max(r) for r in ra) < 1.0  # tracking costs: the copy's vehicles feel the wake


def test_supersuit_copies_give_the_envs_rewards():
    ss = pytest.importorskip("supersuit")
    from downwash_envs.swarm import parallel_env

    direct = parallel_env(preset="stack3", duration=1.0)
    direct.reset(seed=0)
    total_direct = np.zeros(2)
    while direct.agents:
        _, rewards, *_ = direct.step({a: np.zeros(3, np.float32) for a in direct.agents})
        total_direct += [rewards["follower_0"], rewards["follower_1"]]
    venv = ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(parallel_env(preset="stack3", duration=1.0)), 2,
                                 num_cpus=0, base_class="stable_baselines3")
    venv.reset()
    total = np.zeros(4)
    for _ in range(50):
        _, rewards, _, _ = venv.step(np.zeros((4, 3), np.float32))
        total += rewards
    # each copy flies the wake as the env does: the same order of reward, far from the 50 of no motion
    assert np.all(total < 49.0) and np.allclose(total.mean(), total_direct.mean(), rtol=0.5)
