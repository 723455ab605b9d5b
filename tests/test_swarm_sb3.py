"""The swarm env as an SB3 `VecEnv` (downwash_envs.swarm_sb3): SB3's checks, determinism, the same numbers
as the native vector env and as SuperSuit's, same-step autoreset, refusals before any work, PPO end to end."""

import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest

pytest.importorskip("stable_baselines3", reason="the rl extra (stable-baselines3) is not installed")

from stable_baselines3 import PPO  # noqa: E402
from stable_baselines3.common import env_checker  # noqa: E402
from stable_baselines3.common.monitor import Monitor  # noqa: E402
from stable_baselines3.common.vec_env import VecCheckNan, VecMonitor  # noqa: E402

from downwash_core.errors import ConfigError  # noqa: E402
from downwash_core.status import Status  # noqa: E402
from downwash_envs.swarm import SwarmVectorEnv  # noqa: E402
from downwash_envs.swarm_sb3 import SwarmSB3VecEnv, make_vec_env  # noqa: E402

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _actions(seed, n_steps, num_envs):
    return np.random.default_rng(seed).uniform(-1.0, 1.0, (n_steps, num_envs, 3)).astype(np.float32)


def _per_agent(actions, agents, n_worlds):
    """Slot actions (W x A, 3) as the native env's {agent: (W, 3)}."""
    per_world = actions.reshape(n_worlds, len(agents), 3)
    return {a: per_world[:, i] for i, a in enumerate(agents)}


def test_spaces_shapes_dtypes_pass_sb3_checks():
    venv = make_vec_env(3, seed=0, duration=0.2)
    assert venv.num_envs == 3 * 2 and venv.agents == ["follower_0", "follower_1"]
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # SB3 warns about spaces it does not support
        env_checker._check_unsupported_spaces(venv, venv.observation_space, venv.action_space)
        env_checker._check_box_obs(venv.observation_space)
    assert venv.action_space.shape == (3,) and venv.action_space.dtype == np.float32
    checked = VecCheckNan(venv, raise_exception=True)  # raises on a NaN or inf in or out
    obs = checked.reset()
    assert obs.shape == (6, 41) and obs.dtype == np.float32 and len(venv.reset_infos) == 6
    for o in obs:
        env_checker._check_obs(o, venv.observation_space, "reset")
    assert set(venv.reset_infos[0]) == {"sim_seed", "phase"}
    for a in _actions(0, 12, 6):  # through the time limit (10 steps) and its reset
        obs, rewards, dones, infos = checked.step(a)
        assert obs.shape == (6, 41) and obs.dtype == np.float32
        assert rewards.shape == (6,) and rewards.dtype == np.float32
        assert dones.shape == (6,) and dones.dtype == np.bool_
        assert isinstance(infos, list) and len(infos) == 6 and all(isinstance(i, dict) for i in infos)
        for o in obs:
            env_checker._check_obs(o, venv.observation_space, "step")
        assert "autoreset" not in infos[0] and isinstance(infos[0]["TimeLimit.truncated"], bool)
    venv.close()


def test_same_seed_same_actions_bit_identical():
    runs = []
    for _ in range(2):
        venv = make_vec_env(2, seed=7, duration=0.2, n_threads=1)
        out = [venv.reset()]
        for a in _actions(1, 25, venv.num_envs):  # two resets included
            obs, rewards, dones, infos = venv.step(a)
            terminal = [i["terminal_observation"] for i in infos if "terminal_observation" in i]
            out += [obs, rewards, dones, *terminal]
        runs.append(out)
    assert len(runs[0]) == len(runs[1])
    for x, y in zip(*runs):
        assert x.dtype == y.dtype and np.array_equal(x, y)


def test_slots_equal_the_native_vector_env_across_a_reset():
    """Slot w*A + i is agent i of world w; where the native env resets at the step after an end (its actions
    ignored), the adapter resets in the ending step: its terminal observation is the native end, its next
    observation the native new episode's first."""
    W, horizon = 3, 10  # 0.2 s at 50 Hz
    venv = make_vec_env(W, seed=5, duration=0.2)
    native = SwarmVectorEnv(W, duration=0.2)
    agents, A = native.possible_agents, len(native.possible_agents)

    def flat(per_agent):
        return np.stack([per_agent[a] for a in agents], axis=1).reshape(W * A, *per_agent[agents[0]].shape[1:])

    obs = venv.reset()
    native_obs, native_infos = native.reset(seed=5)
    assert np.array_equal(obs, flat(native_obs))
    assert venv.reset_infos[1]["sim_seed"] == native_infos[agents[1]]["sim_seed"][0]
    actions = _actions(2, horizon + 3, W * A)
    for t in range(horizon):
        obs, rewards, dones, infos = venv.step(actions[t])
        n_obs, n_rewards, n_terms, n_truncs, n_infos = native.step(_per_agent(actions[t], agents, W))
        assert np.array_equal(rewards, flat(n_rewards).astype(np.float32))
        assert dones.tolist() == np.repeat(n_terms[agents[0]] | n_truncs[agents[0]], A).tolist()
        assert [i["position_error"] for i in infos] == flat(
            {a: n_infos[a]["position_error"] for a in agents}).tolist()
        if t < horizon - 1:
            assert np.array_equal(obs, flat(n_obs)) and not dones.any()
    assert dones.all() and all(i["TimeLimit.truncated"] for i in infos)
    assert np.array_equal(np.stack([i["terminal_observation"] for i in infos]), flat(n_obs))
    n_obs, n_rewards, *_ , n_infos = native.step(_per_agent(actions[horizon], agents, W))  # the native reset
    assert n_infos[agents[0]]["autoreset"].all()
    assert np.array_equal(obs, flat(n_obs))
    assert [i["sim_seed"] for i in venv.reset_infos] == flat({a: n_infos[a]["sim_seed"] for a in agents}).tolist()
    obs, rewards, dones, _ = venv.step(actions[horizon + 1])  # and on, in step again
    n_obs, n_rewards, *_ = native.step(_per_agent(actions[horizon + 1], agents, W))
    assert np.array_equal(obs, flat(n_obs)) and np.array_equal(rewards, flat(n_rewards).astype(np.float32))


def _readable_step(native, actions):
    """What the adapter's step returns, written out slot by slot on the native env's dict API: slot w*A + i is
    agent i of world w; an ended world is reset in the same step (its slots get terminal_observation and
    TimeLimit.truncated; reset_infos the new episode's info). Returns obs, rewards, dones, infos and
    {slot: new reset info}."""
    agents = native.possible_agents
    W, A = native.n_worlds, len(agents)
    per_world = actions.reshape(W, A, 3)
    obs, rewards, terms, truncs, infos = native.step({a: per_world[:, i] for i, a in enumerate(agents)})
    out_obs, out_rewards, out_dones, out_infos = [], [], [], []
    for w in range(W):
        for a in agents:
            out_obs.append(obs[a][w].copy())
            out_rewards.append(np.float32(rewards[a][w]))
            out_dones.append(bool(terms[a][w] or truncs[a][w]))
            info = {}
            for key, value in infos[a].items():
                if key != "autoreset":
                    info[key] = value[w].item() if value.ndim == 1 else value[w]
            info["TimeLimit.truncated"] = bool(truncs[a][w] and not terms[a][w])
            out_infos.append(info)
    ended = np.array([bool(terms[agents[0]][w] or truncs[agents[0]][w]) for w in range(W)])
    new_reset_infos = {}
    if ended.any():
        new_obs, new_infos = native.reset(options={"reset_mask": ended})
        for w in np.flatnonzero(ended):
            for i, a in enumerate(agents):
                slot = w * A + i
                out_infos[slot]["terminal_observation"] = out_obs[slot]
                out_obs[slot] = new_obs[a][w].copy()
                new_reset_infos[slot] = {k: v[w].item() for k, v in new_infos[a].items() if k != "autoreset"}
    return (np.stack(out_obs), np.array(out_rewards, np.float32), np.array(out_dones), out_infos,
            new_reset_infos)


def _assert_same_info(got, expected):
    assert list(got) == list(expected)  # the same keys, in the same order
    for key, value in expected.items():
        if isinstance(value, np.ndarray):
            assert isinstance(got[key], np.ndarray) and got[key].dtype == value.dtype, key
            assert np.array_equal(got[key], value), key
        else:
            assert type(got[key]) is type(value) and got[key] == value, (key, got[key], value)


def test_step_equals_a_readable_slot_by_slot_construction():
    """The adapter's whole-array step against `_readable_step` on a native env of the same seed, over random
    actions through terminations (a tight tracking box) and time limits, with drawn phases and vehicle scales:
    the same observations, rewards, dones, info dicts (keys, order, value types) and reset infos."""
    from downwash_envs.swarm import SwarmVectorEnv

    options = {"duration": 0.16, "max_tracking_error": 0.05, "action_bound": 15.0, "random_phase": True,
               "randomize": {"mass": 0.1, "motor_lag": 0.2}}
    W = 3
    venv = make_vec_env(W, seed=11, n_threads=1, **options)
    native = SwarmVectorEnv(W, n_threads=1, **options)
    obs = venv.reset()
    native_obs, native_infos = native.reset(seed=11)
    agents, A = native.possible_agents, len(native.possible_agents)
    assert np.array_equal(obs, np.stack([native_obs[a] for a in agents], axis=1).reshape(W * A, -1))
    for slot in range(W * A):
        w, a = divmod(slot, A)
        expected = {k: v[w].item() for k, v in native_infos[agents[a]].items() if k != "autoreset"}
        _assert_same_info(venv.reset_infos[slot], expected)
    terminated = truncated = 0
    for actions in _actions(12, 30, W * A):
        obs, rewards, dones, infos = venv.step(actions)
        r_obs, r_rewards, r_dones, r_infos, r_reset_infos = _readable_step(native, actions)
        assert obs.dtype == np.float32 and obs.shape == r_obs.shape and np.array_equal(obs, r_obs)
        assert rewards.dtype == np.float32 and np.array_equal(rewards, r_rewards)
        assert dones.dtype == np.bool_ and np.array_equal(dones, r_dones)
        assert isinstance(infos, list) and len(infos) == W * A
        for got, expected in zip(infos, r_infos):
            _assert_same_info(got, expected)
        for slot, expected in r_reset_infos.items():
            _assert_same_info(venv.reset_infos[slot], expected)
        terminated += sum(d and not i["TimeLimit.truncated"] for d, i in zip(dones, infos))
        truncated += sum(i["TimeLimit.truncated"] for i in infos)
    assert terminated > 0 and truncated > 0  # both kinds of end were compared
    assert {"mass_scale", "motor_lag_scale"} <= set(infos[0]) and venv.reset_infos[0]["phase"] > 0.0


def test_slots_equal_supersuit_on_the_same_seeds():
    """The adapter is a drop-in for SuperSuit's vector env of ParallelEnv copies: the same slot order, the same
    numbers (copy w of SuperSuit's reset(seed=s) is SwarmEnv.reset(seed=s + w), world w here)."""
    ss = pytest.importorskip("supersuit")
    from downwash_envs.swarm import parallel_env

    W = 2
    venv = make_vec_env(W, seed=3, duration=1.0)
    reference = ss.concat_vec_envs_v1(ss.pettingzoo_env_to_vec_env_v1(parallel_env(duration=1.0)), W, num_cpus=0,
                                      base_class="stable_baselines3")
    obs = venv.reset()
    ref_obs, _ = reference.venv.reset(seed=3)  # (SuperSuit's SB3 wrapper cannot pass a seed on)
    assert np.array_equal(obs, ref_obs)
    for a in _actions(4, 8, venv.num_envs):
        obs, rewards, dones, _ = venv.step(a)
        ref_obs, ref_rewards, ref_dones, _ = reference.step(a)
        assert np.array_equal(obs, ref_obs) and np.array_equal(rewards, ref_rewards.astype(np.float32))
        assert dones.tolist() == ref_dones.tolist()


def test_a_termination_resets_the_world_at_once_and_says_it_was_no_time_limit():
    """A follower driven into the ground ends its world for both agents: done on both slots, the last
    observation in terminal_observation, TimeLimit.truncated False, the other world flies on."""
    venv = make_vec_env(2, seed=0, action_bound=20.0, max_tracking_error=5.0)
    venv.reset()
    down = np.zeros((4, 3), np.float32)
    down[1] = [0.0, 0.0, -1.0]  # world 0's follower_1: -20 m/s^2
    for _ in range(200):
        obs, rewards, dones, infos = venv.step(down)
        if dones.any():
            break
    assert dones.tolist() == [True, True, False, False]
    assert infos[1]["status"] == infos[0]["status"] == int(Status.GROUND)
    assert not infos[0]["TimeLimit.truncated"] and not infos[1]["TimeLimit.truncated"]
    assert "terminal_observation" not in infos[2]
    for slot in (0, 1):
        final = infos[slot]["terminal_observation"]
        assert final.shape == (41,) and not np.array_equal(final, obs[slot])
        assert np.array_equal(obs[slot, 18:21], np.zeros(3, np.float32))  # the new episode: no last action yet
    obs, _, dones, _ = venv.step(np.zeros((4, 3), np.float32))
    assert not dones.any()


def test_bad_input_is_refused_before_any_step():
    with pytest.raises(ConfigError, match="n_worlds"):
        make_vec_env(0)
    with pytest.raises(TypeError, match="SwarmVectorEnv"):
        SwarmSB3VecEnv(object())
    venv = make_vec_env(2, seed=0, duration=0.2, n_threads=1)
    venv.reset()
    t0 = venv.env.simulator.t.copy()
    with pytest.raises(ValueError, match=r"expected shape \(4, 3\)"):
        venv.step_async(np.zeros((2, 3), np.float32))
    bad = np.zeros((4, 3), np.float32)
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match="follower_1"):
        venv.step(bad)
    with pytest.raises(RuntimeError, match="step_async"):
        venv.step_wait()
    with pytest.raises(ValueError, match="no reset options"):
        venv.set_options({"reset_mask": np.ones(2, bool)})
    venv.set_options(None)  # nothing to refuse
    with pytest.raises(IndexError, match="out of range"):
        venv.get_attr("max_steps", indices=[4])
    assert np.array_equal(venv.env.simulator.t, t0)  # nothing stepped
    venv.step(np.zeros((4, 3), np.float32))  # and it still steps


def test_attributes_methods_and_wrappers_are_the_native_envs():
    venv = make_vec_env(2, seed=0, duration=0.2, n_threads=1)
    assert venv.get_attr("max_steps") == [10] * 4 and venv.get_attr("max_steps", indices=1) == [10]
    assert venv.env_method("observation_space", "follower_0", indices=[0, 2]) == [venv.observation_space] * 2
    assert venv.env_is_wrapped(Monitor) == [False] * 4
    venv.set_attr("max_steps", 3)
    venv.reset()
    dones = [venv.step(np.zeros((4, 3), np.float32))[2] for _ in range(3)]
    assert [d.all() for d in dones] == [False, False, True]
    assert venv.seed(10) == [10, 10, 11, 11]  # one seed per world, each of its slots listing it
    with pytest.warns(UserWarning, match="render_mode"):
        assert venv.render() is None  # no render_mode: SB3's warning, no frame


def test_ppo_learns_through_the_adapter():
    venv = VecMonitor(make_vec_env(4, seed=0, duration=0.2, n_threads=1))
    model = PPO("MlpPolicy", venv, n_steps=16, batch_size=64, n_epochs=2, seed=0, device="cpu", verbose=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(384)
    assert model.num_timesteps >= 384
    assert any(not np.array_equal(b.numpy(), p.detach().numpy()) for b, p in zip(before, model.policy.parameters()))
    assert len(model.ep_info_buffer) > 0 and all(e["l"] == 10 for e in model.ep_info_buffer)


def test_render_tiles_each_world_once():
    """A fresh process (MUJOCO_GL is read at `import mujoco`); a missing EGL is a failure here."""
    code = """
        import json
        from stable_baselines3.common.vec_env.base_vec_env import tile_images
        from downwash_envs.swarm_sb3 import make_vec_env
        venv = make_vec_env(2, seed=0, render_mode="rgb_array", render_width=64, render_height=48)
        venv.reset()
        tiled, images = venv.render(), venv.get_images()
        print(json.dumps({"shape": list(tiled.shape), "worlds": list(tile_images(images[::2]).shape),
                          "images": len(images), "std": float(tiled.std())}))
    """
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-4000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["shape"] == res["worlds"] and res["images"] == 4 and res["std"] > 5.0, res
