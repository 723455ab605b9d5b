"""Gymnasium's three autoreset modes on the native vector env: each equals, bit for bit, gymnasium's own
`SyncVectorEnv` of single envs run with the same mode, seeds and actions across episodes ended by
termination and by truncation; bad modes are refused before anything is built; with autoreset disabled a
masked reset restarts only the masked worlds, and stepping an ended world is refused as SyncVectorEnv does."""

import pickle
import re

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode, SyncVectorEnv

from downwash_envs import DownwashFollowerVectorEnv, base  # (importing downwash_envs registers the ids)

N_WORLDS, HORIZON = 3, 12
# a 10 cm tracking box: world 0 (climbing) and world 1 (pushed sideways) leave it within the horizon,
# world 2 (random actions) mostly truncates; episodes end by termination and by truncation
OPTIONS = dict(action_mode="acceleration", reference="hover", separation=(0.3, 0.5), max_tracking_error=0.1)


def _native(mode, **kwargs):
    return gym.make_vec("downwash/Follower-v2", num_envs=N_WORLDS, max_episode_steps=HORIZON,
                        autoreset_mode=mode, **OPTIONS, **kwargs)


def _sync(mode):
    def make():
        return gym.make("downwash/Follower-v2", max_episode_steps=HORIZON, **OPTIONS)

    return SyncVectorEnv([make] * N_WORLDS, autoreset_mode=mode)


def _actions(rng):
    a = rng.uniform(-1.0, 1.0, (N_WORLDS, 3)).astype(np.float32)
    a[0] = [0.0, 0.0, 1.0]  # climbs out of the box (towards the leader)
    a[1] = [1.0, 0.0, 0.0]  # pushed out of the box sideways
    return a


def _same(a, b, where="infos"):
    """Equal values, dtypes and keys, nested dicts and `final_obs`'s object arrays included."""
    if isinstance(a, dict):
        assert isinstance(b, dict) and set(a) == set(b), (where, sorted(a), sorted(b))
        for key in a:
            _same(a[key], b[key], f"{where}[{key!r}]")
    elif a.dtype == object:  # final_obs: one observation per ended world, None elsewhere
        assert b.dtype == object and a.shape == b.shape, where
        for x, y in zip(a, b):
            assert (x is None) == (y is None), where
            if x is not None:
                assert x.dtype == y.dtype and np.array_equal(x, y), (where, x, y)
    else:
        assert a.dtype == b.dtype and np.array_equal(a, b), (where, a, b)


@pytest.mark.parametrize("mode", list(AutoresetMode), ids=lambda m: m.value)
def test_each_mode_equals_sync_vector_env(mode):
    """Same mode, seeds and actions: identical observations, rewards, flags and infos (the ended episodes'
    final_obs and final_info included); with autoreset disabled both are reset through the same masks."""
    vec, syn = _native(mode.value), _sync(mode)
    assert isinstance(vec, DownwashFollowerVectorEnv)
    assert vec.metadata["autoreset_mode"] is syn.metadata["autoreset_mode"] is mode
    r1, r2 = vec.reset(seed=11), syn.reset(seed=11)
    _same(r1[0], r2[0], "obs")
    _same(r1[1], r2[1])
    rng = np.random.default_rng(0)
    terminated = truncated = 0
    for k in range(3 * HORIZON):
        a = _actions(rng)
        r1, r2 = vec.step(a), syn.step(a)
        for name, x, y in zip(("obs", "rewards", "terminations", "truncations"), r1[:4], r2[:4]):
            _same(x, y, name)
        _same(r1[4], r2[4])
        ended = r1[2] | r1[3]
        terminated += int(r1[2].sum())
        truncated += int(r1[3].sum())
        if mode is AutoresetMode.SAME_STEP:
            assert r1[4].get("_final_obs", np.zeros(N_WORLDS, bool)).tolist() == ended.tolist()
        if mode is AutoresetMode.DISABLED and ended.any():  # every other reset seeded
            seeds = [100 + k + i if e and k % 2 else None for i, e in enumerate(ended)]
            r1 = vec.reset(seed=seeds, options={"reset_mask": ended.copy()})
            r2 = syn.reset(seed=seeds, options={"reset_mask": ended.copy()})
            _same(r1[0], r2[0], "obs")
            _same(r1[1], r2[1])
    assert terminated >= 2 and truncated >= 2, (terminated, truncated)
    vec.close()
    syn.close()


def test_the_mode_reaches_the_env_as_an_enum_or_its_value():
    """make_vec's keyword reaches the vector entry point; the default keeps next-step autoreset; the
    mode is per instance and survives pickling (an env pickles as the call that made it)."""
    default = gym.make_vec("downwash/Follower-v2", num_envs=2, reference="hover")
    assert default.metadata["autoreset_mode"] is default.autoreset_mode is AutoresetMode.NEXT_STEP
    same = DownwashFollowerVectorEnv(2, reference="hover", autoreset_mode=AutoresetMode.SAME_STEP)
    assert same.metadata["autoreset_mode"] is same.autoreset_mode is AutoresetMode.SAME_STEP
    assert DownwashFollowerVectorEnv.metadata["autoreset_mode"] is AutoresetMode.NEXT_STEP  # the class's untouched
    copy = pickle.loads(pickle.dumps(same))
    assert copy.metadata["autoreset_mode"] is AutoresetMode.SAME_STEP
    for env in (default, same, copy):
        env.close()


@pytest.mark.parametrize("bad", ["same_step", "SAME_STEP", "", None, 1, True])
def test_a_bad_mode_names_the_allowed_ones_before_anything_is_built(bad, monkeypatch):
    def build(*args, **kwargs):
        raise AssertionError("worlds built before the autoreset mode was checked")

    monkeypatch.setattr(base, "FollowerWorlds", build)
    message = re.escape(f"autoreset_mode: got {bad!r}; allowed: AutoresetMode.NEXT_STEP ('NextStep'), "
                        "AutoresetMode.SAME_STEP ('SameStep'), AutoresetMode.DISABLED ('Disabled')")
    with pytest.raises(ValueError, match=f"^{message}$"):
        gym.make_vec("downwash/Follower-v2", num_envs=2, autoreset_mode=bad)
    with pytest.raises(ValueError, match=f"^{message}$"):
        DownwashFollowerVectorEnv(2, autoreset_mode=bad)


def test_the_single_env_points_a_sync_make_vec_to_vector_kwargs():
    """make_vec(..., vectorization_mode="sync") hands its keywords to each single env; the mode belongs
    in vector_kwargs there, which SyncVectorEnv takes."""
    with pytest.raises(TypeError, match=r"autoreset_mode: an option of the vector env.*vector_kwargs"):
        gym.make_vec("downwash/Follower-v2", num_envs=2, vectorization_mode="sync", autoreset_mode="SameStep")


def _ended_disabled_env():
    """A disabled-autoreset env whose three worlds all truncated at the last step (hover, no push)."""
    vec = gym.make_vec("downwash/Follower-v2", num_envs=N_WORLDS, max_episode_steps=3, reference="hover",
                       autoreset_mode="Disabled")
    vec.reset(seed=5)
    for _ in range(3):
        obs, _, terminated, truncated, _ = vec.step(np.zeros((N_WORLDS, 3), np.float32))
    assert truncated.all() and not terminated.any()
    return vec, obs


def test_disabled_mode_reset_mask_resets_only_the_masked_worlds():
    vec, last = _ended_disabled_env()
    t_end = vec.simulator.t.copy()
    mask = np.array([True, False, True])
    obs, infos = vec.reset(options={"reset_mask": mask})
    assert np.array_equal(vec.simulator.t, np.where(mask, 0.0, t_end))
    assert np.array_equal(obs[1], last[1]) and not np.array_equal(obs[[0, 2]], last[[0, 2]])
    assert infos["_separation"].tolist() == mask.tolist()
    with pytest.raises(AssertionError, match=r"world\(s\) \[1\] has ended"):  # world 1 still waits for its reset
        vec.step(np.zeros((N_WORLDS, 3), np.float32))
    vec.reset(options={"reset_mask": ~mask})
    _, _, terminated, truncated, _ = vec.step(np.zeros((N_WORLDS, 3), np.float32))
    assert not (terminated | truncated).any() and np.all(vec.simulator.t > 0.0)
    vec.close()


def test_stepping_an_ended_world_with_autoreset_disabled_raises_as_sync_vector_env_does():
    """SyncVectorEnv asserts; the native env raises an AssertionError too (also a ResetNeeded), before
    any world steps."""
    vec, _ = _ended_disabled_env()
    t_end = vec.simulator.t.copy()
    with pytest.raises(AssertionError) as raised:
        vec.step(np.zeros((N_WORLDS, 3), np.float32))
    assert isinstance(raised.value, gym.error.ResetNeeded)
    assert "reset_mask" in str(raised.value)
    assert np.array_equal(vec.simulator.t, t_end)  # nothing stepped
    syn = SyncVectorEnv([lambda: gym.make("downwash/Follower-v2", max_episode_steps=3, reference="hover")],
                        autoreset_mode=AutoresetMode.DISABLED)
    syn.reset(seed=5)
    for _ in range(3):
        syn.step(np.zeros((1, 3), np.float32))
    with pytest.raises(AssertionError):
        syn.step(np.zeros((1, 3), np.float32))
    vec.close()
    syn.close()
