"""The stable-baselines3 adapter of the native vector env: the same episodes as SB3's own
`DummyVecEnv` of single envs, SB3's checker passes, and PPO trains through it."""

import warnings

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")

from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common.env_checker import check_env  # noqa: E402
from stable_baselines3.common.vec_env import DummyVecEnv  # noqa: E402

import downwash_envs  # noqa: E402,F401
from downwash_envs.sb3 import SB3VecEnv, make_vec_env  # noqa: E402

# short episodes and a tight tracking box with large actions: both truncations and
# terminations (crashes) happen within the test's steps
OPTIONS = dict(max_episode_steps=20, max_tracking_error=0.25, action_mode="acceleration")


def test_adapter_gives_the_episodes_of_dummy_vec_env():
    n, seed = 3, 11
    native = make_vec_env("downwash/Follower-v2", num_envs=n, seed=seed, **OPTIONS)
    dummy = DummyVecEnv([lambda: gym.make("downwash/Follower-v2", **OPTIONS) for _ in range(n)])
    dummy.seed(seed)
    a, b = native.reset(), dummy.reset()
    np.testing.assert_array_equal(a, b)
    rng = np.random.default_rng(0)
    ends = {"terminated": 0, "truncated": 0}
    for _ in range(60):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        actions[0] = np.clip(actions[0] + [0.9, 0.0, 0.0], -1, 1)  # world 0 drifts out of the box
        (oa, ra, da, ia), (ob, rb, db, ib) = native.step(actions), dummy.step(actions)
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(da, db)
        for i in range(n):
            assert ia[i]["TimeLimit.truncated"] == ib[i]["TimeLimit.truncated"]
            assert ("terminal_observation" in ia[i]) == ("terminal_observation" in ib[i]) == bool(da[i])
            if da[i]:
                np.testing.assert_array_equal(ia[i]["terminal_observation"], ib[i]["terminal_observation"])
                ends["truncated" if ia[i]["TimeLimit.truncated"] else "terminated"] += 1
            assert ia[i]["position_error"] == ib[i]["position_error"]
    assert ends["terminated"] > 0 and ends["truncated"] > 0, ends
    native.close()
    dummy.close()


def test_adapter_over_sync_vector_env_gives_the_same_episodes():
    """The adapter serves any next-step-autoreset vector env: Gymnasium's SyncVectorEnv of the
    single envs gives the native env's episodes through it."""
    n, seed = 2, 5
    native = make_vec_env("downwash/Follower-v2", num_envs=n, seed=seed, **OPTIONS)
    sync = SB3VecEnv(gym.vector.SyncVectorEnv([lambda: gym.make("downwash/Follower-v2", **OPTIONS)] * n))
    sync.seed(seed)
    np.testing.assert_array_equal(native.reset(), sync.reset())
    rng = np.random.default_rng(1)
    for _ in range(40):
        actions = rng.uniform(-1, 1, (n, 3)).astype(np.float32)
        actions[0] = np.clip(actions[0] + [0.9, 0.0, 0.0], -1, 1)
        (oa, ra, da, ia), (ob, rb, db, ib) = native.step(actions), sync.step(actions)
        np.testing.assert_array_equal(oa, ob)
        np.testing.assert_array_equal(ra, rb)
        np.testing.assert_array_equal(da, db)
        for i in np.flatnonzero(da):
            np.testing.assert_array_equal(ia[i]["terminal_observation"], ib[i]["terminal_observation"])


def test_sb3_checker_passes_without_warnings():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        check_env(gym.make("downwash/Follower-v2"), warn=True)


def test_ppo_trains_through_the_adapter():
    venv = make_vec_env(num_envs=4, seed=0)
    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=32, n_epochs=1, seed=0, device="cpu")
    model.learn(64)
    assert model.num_timesteps == 64


def test_the_adapter_refuses_a_same_step_autoreset_env():
    env = gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1")], autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)
    with pytest.raises(ValueError, match="next-step autoreset"):
        SB3VecEnv(env)
