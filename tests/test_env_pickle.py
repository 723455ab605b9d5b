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


def _zeros(env):
    """Zero actions for every env kind (a dict per agent for the swarm envs)."""
    if hasattr(env, "possible_agents"):
        shape = (3,) if not hasattr(env, "n_worlds") else (env.n_worlds, 3)
        return {a: np.zeros(shape, np.float32) for a in env.possible_agents}
    return np.zeros(env.action_space.shape, np.float32)


def _swarm(vector):
    pytest.importorskip("pettingzoo")
    from downwash_envs.swarm import SwarmVectorEnv, parallel_env

    return SwarmVectorEnv(2, preset="stack3", duration=0.5) if vector else parallel_env(preset="stack3", duration=0.5)


@pytest.mark.parametrize("make", [
    lambda: DownwashFollowerEnv(reference="hover", separation=0.6),
    lambda: DownwashFollowerVectorEnv(2, reference="hover", separation=0.6),
    lambda: _swarm(vector=False),
    lambda: _swarm(vector=True),
], ids=["single", "vector", "swarm", "swarm_vector"])  # fmt: skip
def test_an_unpickled_copy_needs_a_reset_before_it_steps(make):
    """The copy is a new env (the decorator's contract: the simulator cannot be copied, so neither can the
    episode): stepping it before reset() raises gymnasium's ResetNeeded rather than flying its
    placeholder state; after reset() it flies as a fresh env does."""
    env = make()
    env.reset(seed=3)
    env.step(_zeros(env))
    copy = pickle.loads(pickle.dumps(env))
    with pytest.raises(gym.error.ResetNeeded, match=r"call reset\(\) first"):
        copy.step(_zeros(copy))
    assert np.all(copy.simulator.t == 0.0)  # nothing stepped
    fresh = make()
    for e in (copy, fresh):
        e.reset(seed=5)
    a, b = fresh.step(_zeros(fresh)), copy.step(_zeros(copy))
    assert pickle.dumps(a) == pickle.dumps(b)


def test_an_unpickled_made_env_needs_a_reset_and_then_runs_a_whole_episode():
    """Through gym.make the wrappers pickle their own state (OrderEnforcing: reset done; TimeLimit: 100 steps
    elapsed) around a new inner env: the copy used to fly that unreset env and truncate after 400 steps. It
    now refuses to step until reset(), and then runs the registered 500."""
    env = gym.make("downwash/Follower-v2", reference="hover")
    env.reset(seed=0)
    for _ in range(100):
        env.step(np.zeros(3, np.float32))
    copy = pickle.loads(pickle.dumps(env))
    with pytest.raises(gym.error.ResetNeeded, match=r"step\(\) before reset\(\)"):
        copy.step(np.zeros(3, np.float32))
    copy.reset(seed=0)
    for n in range(1, 501):
        *_, terminated, truncated, _ = copy.step(np.zeros(3, np.float32))
        if terminated or truncated:
            break
    assert (n, terminated, truncated) == (500, False, True)
