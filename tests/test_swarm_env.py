"""The multi-agent swarm env (downwash_envs.swarm): PettingZoo's API test, determinism, batched == serial,
the neighbour observation's properties, zero action == the baseline flight, shared episode ends,
bad input, the documented table, rendering."""

import inspect
import json
import os
import subprocess
import sys
import textwrap
import warnings

import numpy as np
import pytest
from gymnasium import error as gym_error
from hypothesis import given, settings
from hypothesis import strategies as st
from pettingzoo.test import parallel_api_test

import downwash_envs.swarm as swarm
from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConfigError
from downwash_core.geometry import quat_to_mat
from downwash_core.status import Status
from downwash_envs.swarm import (
    NEIGHBOUR_DIM,
    OWN_DIM,
    SwarmEnv,
    SwarmVectorEnv,
    neighbour_block,
    obs_dim,
    obs_slices,
    parallel_env,
)
from downwash_envs.task import ERROR_CAP, REWARD_TERMS, task_constants, task_kernel, task_terms
from sim.field import DownwashField, pairwise_field
from sim.flight import fly
from sim.presets import make_preset
from sim.simulator import Simulator

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def _random_actions(rng, agents, scale=2.0, n_worlds=None):
    shape = (3,) if n_worlds is None else (n_worlds, 3)
    return {a: (scale * rng.uniform(-1.0, 1.0, shape)).astype(np.float32) for a in agents}


# ----------------------------------------------------------------------------- API contract


@pytest.mark.parametrize("preset", ["stack3", "formation5"])
def test_pettingzoo_parallel_api(preset):
    """PettingZoo's own checker, through truncation (1 s = 50 steps) and two resets."""
    env = parallel_env(preset=preset, duration=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the checker's reset(options={"options": 1}) draws our warning
        parallel_api_test(env, num_cycles=60)
    n_vehicles = make_preset(preset).n_vehicles
    # named by role and rank (one group in TorchRL/BenchMARL), in scene order
    assert env.possible_agents == [f"follower_{k}" for k in range(make_preset(preset).n_vehicles - 1)]
    assert env.observation_space("follower_0").shape == (OWN_DIM + NEIGHBOUR_DIM * (n_vehicles - 1),)


def test_rollout_stays_in_the_spaces_and_reward_is_the_sum_of_its_terms():
    env = parallel_env(preset="formation5", max_neighbours=6)  # 4 others, 2 padded slots
    rng = np.random.default_rng(0)
    obs, infos = env.reset(seed=3)
    assert set(infos["follower_0"]) == {"sim_seed", "phase"}
    for _ in range(40):
        for a, o in obs.items():
            assert env.observation_space(a).contains(o), a
        obs, rewards, term, trunc, infos = env.step(_random_actions(rng, env.agents))
        for a in env.possible_agents:
            assert rewards[a] == sum(infos[a][f"reward_{k}"] for k in REWARD_TERMS)
            assert isinstance(rewards[a], float) and infos[a]["field_mean"].shape == (3,)
        if not env.agents:
            break
    # the padded slots (k = 4, 5) are zero with mask 0; the real ones have mask 1
    s = obs_slices(6)
    for o in obs.values():
        assert [o[s[f"n{k}_mask"]][0] for k in range(6)] == [1, 1, 1, 1, 0, 0]
        assert not o[s["n4_mask"].start:].any()


# ----------------------------------------------------------------------------- determinism


def _rollout(env, seed, n_steps, action_seed):
    rng = np.random.default_rng(action_seed)
    obs, info = env.reset(seed=seed)
    out = [(obs, info)]
    for _ in range(n_steps):
        if not env.agents:
            break
        out.append(env.step(_random_actions(rng, env.agents)))
    return out


def _assert_same(a, b):
    if isinstance(a, dict):
        assert a.keys() == b.keys()
        for k in a:
            _assert_same(a[k], b[k])
    elif isinstance(a, (tuple, list)):
        assert len(a) == len(b)
        for x, y in zip(a, b):
            _assert_same(x, y)
    else:
        np.testing.assert_array_equal(a, b)


def test_same_seed_same_actions_same_trajectory_bit_for_bit():
    a = _rollout(parallel_env(preset="stack3", random_phase=True), seed=7, n_steps=60, action_seed=1)
    b = _rollout(parallel_env(preset="stack3", random_phase=True), seed=7, n_steps=60, action_seed=1)
    assert len(a) == 61
    _assert_same(a, b)
    c = _rollout(parallel_env(preset="stack3", random_phase=True), seed=8, n_steps=5, action_seed=1)
    assert not np.array_equal(a[5][0]["follower_0"], c[5][0]["follower_0"])  # the seed matters
    assert a[0][1]["follower_0"]["phase"] != c[0][1]["follower_0"]["phase"]
    # the provenance is stable JSON, and names what differs
    d = [json.dumps(swarm.make_swarm_config(preset=p, random_phase=True).describe()) for p in ("stack3", "stack3", "stack4")]
    assert d[0] == d[1] != d[2]


# ----------------------------------------------------------------------------- batched == serial


def test_vector_world_k_equals_the_parallel_env_with_its_seed():
    """stack4 (4 vehicles, 3 agents): world k of SwarmVectorEnv(3).reset(seed=s) is SwarmEnv.reset(seed=s + k),
    bit for bit, through truncation and the vector env's autoreset into the next episode."""
    W, T, seed = 3, 25, 10
    opts = dict(preset="stack4", duration=T * 0.02, random_phase=True)
    vec = SwarmVectorEnv(W, **opts)
    singles = [SwarmEnv(**opts) for _ in range(W)]
    rng = np.random.default_rng(0)
    v_obs, v_info = vec.reset(seed=seed)
    s_out = [env.reset(seed=seed + k) for k, env in enumerate(singles)]
    for k in range(W):
        for a in vec.agents:
            np.testing.assert_array_equal(v_obs[a][k], s_out[k][0][a])
            assert v_info[a]["sim_seed"][k] == s_out[k][1][a]["sim_seed"]
    for step in range(T + 1):
        actions = _random_actions(rng, vec.agents, n_worlds=W)
        v_obs, v_rew, v_term, v_trunc, v_info = vec.step(actions)
        for k, env in enumerate(singles):
            if step < T:
                obs, rew, term, trunc, info = env.step({a: actions[a][k] for a in env.agents})
            else:  # the vector env resets world k now: the single env's next episode
                obs, info = env.reset()
                rew = dict.fromkeys(env.possible_agents, 0.0)
                term = trunc = dict.fromkeys(env.possible_agents, False)
            for a in vec.agents:
                np.testing.assert_array_equal(v_obs[a][k], obs[a])
                assert v_rew[a][k] == rew[a] and v_term[a][k] == term[a] and v_trunc[a][k] == trunc[a]
                if step < T:
                    for key, value in info[a].items():
                        np.testing.assert_array_equal(v_info[a][key][k], value, err_msg=key)
                else:
                    assert v_info[a]["autoreset"][k] and v_info[a]["sim_seed"][k] == info[a]["sim_seed"]
        if step == T - 1:  # the episodes end by truncation, in every world, for every agent
            assert all(v_trunc[a].all() and not v_term[a].any() for a in vec.agents)


# ----------------------------------------------------------------------------- observation


def _random_scene(rng, W, V):
    pos = rng.normal(size=(W, V, 3))
    vel = rng.normal(size=(W, V, 3))
    q = rng.normal(size=(W, V, 4))
    rot = quat_to_mat(q / np.linalg.norm(q, axis=-1, keepdims=True))
    return pos, vel, rot


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), V=st.integers(2, 8), K=st.integers(1, 7))
def test_neighbour_slots_are_sorted_masked_and_do_not_depend_on_scene_order(seed, V, K):
    rng = np.random.default_rng(seed)
    W = 3
    pos, vel, rot = _random_scene(rng, W, V)
    agents = np.arange(1, V)
    nb = neighbour_block(pos, vel, rot, agents, K)
    assert nb.shape == (W, V - 1, K, NEIGHBOUR_DIM)
    n = min(K, V - 1)
    # mask: the first min(K, V-1) slots; padding is all zero
    np.testing.assert_array_equal(nb[..., 0], np.broadcast_to(np.arange(K) < n, (W, V - 1, K)))
    assert not nb[..., n:, :].any()
    # slots hold the nearest vehicles, nearest first: distances nondecreasing, and the K nearest
    dist = np.linalg.norm(nb[..., :n, 1:4], axis=-1)
    assert np.all(np.diff(dist, axis=-1) >= 0)
    for w in range(W):
        for i, a in enumerate(agents):
            all_d = np.sort([np.linalg.norm(pos[w, a] - pos[w, j]) for j in range(V) if j != a])
            np.testing.assert_allclose(dist[w, i], all_d[:n], rtol=1e-12)
            # each slot is one real vehicle: dp, dv and its z axis belong together
            for k in range(n):
                j = int(np.argmin(np.linalg.norm(pos[w] - (pos[w, a] - nb[w, i, k, 1:4]), axis=-1)))
                np.testing.assert_array_equal(nb[w, i, k, 1:4], pos[w, a] - pos[w, j])
                np.testing.assert_array_equal(nb[w, i, k, 4:7], vel[w, a] - vel[w, j])
                np.testing.assert_array_equal(nb[w, i, k, 7:10], rot[w, j, :, 2])
    # relabel the vehicles (the scene order): each agent's slots are unchanged, bit for bit
    perm = rng.permutation(V)  # new index of old vehicle i is inv[i]
    inv = np.argsort(perm)
    nb_perm = neighbour_block(pos[:, perm], vel[:, perm], rot[:, perm], inv[agents], K)
    np.testing.assert_array_equal(nb_perm, nb)
    # a world's slots do not depend on the batch it is in
    np.testing.assert_array_equal(neighbour_block(pos[1:2], vel[1:2], rot[1:2], agents, K), nb[1:2])


def test_the_env_sees_the_neighbour_sets_the_data_and_predictor_see():
    """One selection (`sim.neighbours`): a diverged vehicle (NaN or infinite state) is no neighbour
    in the env's observation either; before, it filled a real slot there while the data masked it."""
    from sim.neighbours import NeighbourSet, select_neighbours

    rng = np.random.default_rng(3)
    W, V, K = 3, 5, 4
    pos, vel, rot = _random_scene(rng, W, V)
    pos[1, 2] = np.nan
    pos[2, 4] = np.inf
    agents = np.arange(V)
    nb = neighbour_block(pos, vel, rot, agents, K)
    index, mask = select_neighbours(pos, NeighbourSet(K))
    np.testing.assert_array_equal(nb[..., 0], mask)
    for w, bad in ((1, 2), (2, 4)):
        others = [a for a in agents if a != bad]
        assert not (index[w, others] == bad).any()  # never anyone's neighbour
        assert mask[w, others].sum(axis=-1).tolist() == [V - 2] * len(others)  # the rest still are
        assert not mask[w, bad].any()  # and it sees no one
    for w in range(W):
        for a in agents:
            for k in np.flatnonzero(mask[w, a]):
                np.testing.assert_array_equal(nb[w, a, k, 1:4], pos[w, a] - pos[w, index[w, a, k]])


@pytest.mark.parametrize("seed", range(6))
def test_compiled_observation_equals_the_readable_one(seed):
    """`observe_kernel` against `observation` (own block + neighbour_block), bit for bit, over random
    states with exact distance ties (positions in whole metres) and a diverged (NaN) world."""
    rng = np.random.default_rng(seed)
    W, V = 4, int(rng.integers(2, 9))
    K = int(rng.integers(1, 8))
    pos, vel, rot = _random_scene(rng, W, V)
    pos = np.round(3.0 * pos)  # whole metres: exact distance ties are common
    pos[3, 1] = np.nan  # a diverged world
    ref = type("Ref", (), {})()
    ref.pos, ref.vel, ref.acc = (rng.normal(size=(W, V, 3)) * 20 for _ in range(3))  # some beyond the bounds
    agents = np.arange(1, V) if seed % 2 else rng.permutation(V)[: max(1, V // 2)]
    last = rng.normal(size=(W, len(agents), 3))
    low, high = swarm.swarm_obs_bounds(K, 5.0)
    want = swarm.swarm_observation(pos, vel, rot, ref, agents, last, K, low, high)
    got = np.empty_like(want)
    swarm.observe_kernel(pos, vel, rot, ref.pos, ref.vel, ref.acc, agents, last, low, high, got)
    np.testing.assert_array_equal(got, want)
    assert np.all(want >= low) and np.all(want <= high) and np.isfinite(want).all()


@pytest.mark.parametrize("seed", range(4))
def test_compiled_reward_and_termination_equal_the_readable_ones(seed):
    """`_task_kernel` against `task_terms`, bit for bit: random states, some agents outside the box,
    a crashed world, a diverged (NaN) one, non-default weights."""
    rng = np.random.default_rng(seed)
    W, V = 6, int(rng.integers(2, 9))
    agents = np.arange(1, V)
    ref_pos, ref_vel, true_vel = (rng.normal(size=(W, V, 3)) for _ in range(3))
    spread = np.array([0.05, 0.05, 1.0, 0.05, 0.05, 0.05])[:, None, None]  # m: world 2 far off its references
    true_pos = ref_pos + spread * rng.normal(size=(W, V, 3))
    true_pos[4, 1] = np.nan
    true_vel[5, -1] = 1e3  # beyond the cap
    actions, last = rng.uniform(-5, 5, (W, V - 1, 3)), rng.uniform(-5, 5, (W, V - 1, 3))
    sim_status = np.array([0, 0, 0, int(Status.GROUND), int(Status.DIVERGED), 0], np.int64)
    task = swarm.make_config({"max_tracking_error": 0.9, "alive_reward": 0.3, "action_cost_weight": 0.7})
    constants = task_constants(task, 5.0)
    status, terms, reward, pos_err, vel_err = task_terms(
        true_pos, true_vel, ref_pos, ref_vel, agents, actions, last, sim_status, constants)
    out = (np.empty(W, np.int64), np.empty((6, W, V - 1)), *(np.empty((W, V - 1)) for _ in range(3)))
    task_kernel(true_pos, true_vel, ref_pos, ref_vel, agents, actions, last, sim_status, constants, *out)
    for got, want in zip(out, (status, terms, reward, pos_err, vel_err)):
        np.testing.assert_array_equal(got, want)
    assert status[3] == Status.GROUND and status[4] == Status.DIVERGED and pos_err[4, 0] == ERROR_CAP
    assert vel_err[5, -1] == ERROR_CAP
    for w in range(W):  # LEFT_BOX exactly where a live world has an agent outside the box
        if sim_status[w] == 0:
            assert (status[w] == Status.LEFT_BOX) == bool((pos_err[w] > 0.9).any())
    assert np.all(terms[0][status != 0] == 0.0) and np.all(terms[5][status != 0] == -50.0)
    assert np.all(terms[0][status == 0] == 0.3) and (status == 0).any() and status[2] == Status.LEFT_BOX


def test_env_observation_is_the_documented_layout_of_the_estimated_state():
    env = parallel_env(preset="stack4", max_neighbours=5)
    rng = np.random.default_rng(2)
    env.reset(seed=1)
    for _ in range(20):
        obs, *_ = env.step(_random_actions(rng, env.agents, scale=1.0))
    sim = env.simulator
    pe, ve, rot, ref = sim.pos_est[0], sim.vel_est[0], sim.true_states().rot[0], sim.reference(sim.t)
    assert not np.array_equal(pe, sim.true_states().pos[0])  # estimates, not the truth
    s = obs_slices(5)
    assert len(obs["follower_1"]) == obs_dim(5) == 71
    def f32(x):  # the observation is float32: the float64 state rounded once
        return np.asarray(x, np.float64).astype(np.float32)

    for a, name in enumerate(env.possible_agents):
        i = int(env._worlds.agent_index[a])  # the vehicle this agent flies
        o = obs[name]
        np.testing.assert_array_equal(o[s["pos_error"]], f32(pe[i] - ref.pos[0, i]))
        np.testing.assert_array_equal(o[s["v_follower"]], f32(ve[i]))
        np.testing.assert_array_equal(o[s["follower_z_axis"]], f32(rot[i, :, 2]))
        others = [j for j in range(4) if j != i]
        d = sorted((np.linalg.norm(pe[i] - pe[j]), j) for j in others)
        for k, (_, j) in enumerate(d):
            assert o[s[f"n{k}_mask"]][0] == 1.0
            np.testing.assert_array_equal(o[s[f"n{k}_dp"]], f32(pe[i] - pe[j]))
            np.testing.assert_array_equal(o[s[f"n{k}_z_axis"]], f32(rot[j, :, 2]))
        assert o[s["n3_mask"]][0] == 0.0 and not o[s["n3_mask"].start:].any()


def test_docstring_table_is_the_generated_one():
    assert swarm.swarm_observation_table() in swarm.__doc__


# ----------------------------------------------------------------------------- physics


def test_zero_action_flies_the_baseline_controller_bit_for_bit():
    """Action 0 everywhere is `sim.flight.fly` of the preset with the same noise seed."""
    env = parallel_env(preset="stack3")
    _, info = env.reset(seed=4)
    T = 60
    pos = []
    for _ in range(T):
        env.step({a: np.zeros(3, np.float32) for a in env.agents})
        pos.append(env.simulator.true_states().pos[0].copy())
    preset = make_preset("stack3")
    log, = fly(preset.scene(), preset.reference(1), [info["follower_0"]["sim_seed"]], (T + 1) * env.dt,
               field=DownwashField(), controller=FeedbackLinearisedLQR())
    np.testing.assert_array_equal(np.array(pos), log.arrays["pos"][1:T + 1])


def test_info_field_is_the_true_field_on_each_agent():
    env = parallel_env(preset="stack3")
    env.reset(seed=0)
    for _ in range(5):
        before = env.simulator.true_states()  # the step's first autopilot tick senses this state
        _, _, _, _, infos = env.step({a: np.zeros(3, np.float32) for a in env.agents})
    mean = pairwise_field(DownwashField(), before.pos, before.vel, before.rot)[0]
    np.testing.assert_array_equal(infos["follower_0"]["field_mean"], mean[1])
    np.testing.assert_array_equal(infos["follower_1"]["field_mean"], mean[2])
    assert mean[1, 2] < -0.3  # bravo is in alpha's downwash


def test_a_collision_ends_the_world_for_every_agent():
    """Charlie driven into the ground: the crash terminates bravo and charlie alike, both penalised."""
    env = parallel_env(preset="stack3", action_bound=20.0, max_tracking_error=5.0)
    env.reset(seed=0)
    for _ in range(200):
        down = np.array([0.0, 0.0, -1.0], np.float32)  # normalised: -20 m/s^2
        obs, rew, term, trunc, infos = env.step({"follower_0": np.zeros(3, np.float32), "follower_1": down})
        if not env.agents:
            break
    assert term == {"follower_0": True, "follower_1": True} and not any(trunc.values())
    assert infos["follower_1"]["status"] == infos["follower_0"]["status"] == int(Status.GROUND)
    assert infos["follower_1"]["reward_termination"] == -50.0 and infos["follower_1"]["reward_alive"] == 0.0
    with pytest.raises(RuntimeError, match="reset"):
        env.step({})


def test_a_nonlinear_aggregation_reaches_the_flight():
    """With the simulator's aggregation slot, a shielding law changes the field on the bottom of a stack;
    without it (the slot is being added), the env refuses the law by name before building anything."""
    if "aggregation" not in inspect.signature(Simulator).parameters:
        with pytest.raises(ConfigError, match="aggregation: 'shielding' needs the simulator's aggregation slot"):
            parallel_env(preset="stack4", aggregation="shielding")
        return
    fields = {}
    for law in ("linear", "shielding"):
        env = parallel_env(preset="stack4", aggregation=law)
        env.reset(seed=0)
        for _ in range(3):
            *_, infos = env.step({a: np.zeros(3, np.float32) for a in env.agents})
        fields[law] = infos["follower_2"]["field_mean"]
    assert not np.allclose(fields["linear"], fields["shielding"], rtol=0.0, atol=1e-6)


# ----------------------------------------------------------------------------- bad input


@pytest.mark.parametrize("kwargs, match", [
    ({"preset": "stack9"}, "preset: unknown"),
    ({"preset": "stack:n=9"}, "n: a stack has 2-8"),
    ({"aggregation": "cubic"}, "aggregation.*'cubic'.*allowed: linear"),
    ({"field": "nofield"}, "field"),
    ({"max_neighbours": 0}, "max_neighbours"),
    ({"max_neighbours": 8}, "max_neighbours"),
    ({"duration": -1.0}, "duration"),
    ({"duration": 0.001}, "duration: 0.001 s is shorter than one env step"),
    ({"action_bound": 50.0}, "action_bound"),
    # strings and bools are not numbers (float() would read them as 1.0, 0.5, ...)
    ({"duration": "1.0"}, r"duration: expected a number, got '1.0' \(a str.*allowed \(0.0, 100000.0\] s"),
    ({"duration": True}, r"duration: expected a number, got True \(a bool.*allowed \(0.0, 100000.0\] s"),
    ({"action_bound": "5"}, r"action_bound: expected a number.*allowed \(0.0, 20.0\] m/s\^2"),
    ({"max_tracking_error": True}, r"max_tracking_error: expected a number.*allowed \(0.0, 5.0\] m"),
    ({"termination_penalty": "50"}, r"termination_penalty: expected a number.*allowed \[0.0, 1000000.0\]"),
    ({"randomize": {"mass": "0.1"}}, r"randomize\['mass'\]: expected a number.*allowed \[0.0, 0.5\]"),
])  # fmt: skip
def test_bad_options_raise_config_error_before_any_simulation(kwargs, match, monkeypatch):
    def no_sim(*args, **kw):
        raise AssertionError("a Simulator was built before the options were checked")

    monkeypatch.setattr(swarm, "Simulator", no_sim)
    with pytest.raises(ConfigError, match=match):
        parallel_env(**kwargs)
    with pytest.raises(ConfigError, match=match):
        SwarmVectorEnv(2, **kwargs)


def test_bad_names_and_actions():
    with pytest.raises(TypeError, match="separation.*allowed: preset"):
        parallel_env(separation=0.5)  # a single-env option that does not apply to a preset
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):  # Python's wording
        parallel_env(frameskip=2)
    with pytest.raises(ValueError, match="render_mode"):
        parallel_env(render_mode="bogus")
    env = parallel_env(preset="stack3")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"missing \['follower_1'\]"):
        env.step({"follower_0": np.zeros(3)})
    with pytest.raises(ValueError, match=r"unexpected \['alpha'\]"):
        env.step({"follower_0": np.zeros(3), "follower_1": np.zeros(3), "alpha": np.zeros(3)})
    with pytest.raises(ValueError, match="finite"):
        env.step({"follower_0": np.array([np.nan, 0, 0]), "follower_1": np.zeros(3)})
    with pytest.raises(ValueError, match=r"shape \(3,\)"):
        env.step({"follower_0": np.zeros(2), "follower_1": np.zeros(3)})
    vec = SwarmVectorEnv(2, preset="stack3")
    vec.reset(seed=0)
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        vec.step({"follower_0": np.zeros(3), "follower_1": np.zeros(3)})
    with pytest.raises(ValueError, match="reset_mask"):
        vec.reset(options={"reset_mask": np.zeros(2, bool)})


def test_vector_env_array_api_equals_its_dict_api():
    """`reset_arrays` / `step_arrays` (the SB3 adapter's path) are `reset` / `step` without the per-agent dicts:
    the same observations, rewards, ends and info columns on twin envs, through a truncation and the next-step
    autoreset; a NaN action is refused with the dict path's message (naming the agent), a wrong shape too."""
    W, opts = 3, {"preset": "stack4", "duration": 0.1, "random_phase": True, "randomize": {"mass": 0.1}}
    twins = SwarmVectorEnv(W, n_threads=1, **opts), SwarmVectorEnv(W, n_threads=1, **opts)
    by_dict, by_array = twins
    agents = by_dict.possible_agents
    obs, infos = by_dict.reset(seed=4)
    arr_obs, mask = by_array.reset_arrays(seed=4)
    assert mask.all() and arr_obs.dtype == np.float32 and arr_obs.shape == (W, len(agents), obs_dim(3))
    for i, a in enumerate(agents):
        np.testing.assert_array_equal(arr_obs[:, i], obs[a])
        for key, column in by_array.episode_arrays.items():
            np.testing.assert_array_equal(column[:, i], infos[a][key], err_msg=key)
    rng = np.random.default_rng(1)
    for _ in range(8):  # 5 steps to the time limit, then the autoreset step, then on
        actions = rng.uniform(-1.2, 1.2, (W, len(agents), 3)).astype(np.float32)
        obs, rewards, terms, truncs, infos = by_dict.step({a: actions[:, i] for i, a in enumerate(agents)})
        result = by_array.step_arrays(actions)
        for i, a in enumerate(agents):
            np.testing.assert_array_equal(result.obs[:, i], obs[a])
            np.testing.assert_array_equal(result.outcome.info["reward"][:, i], rewards[a])
            assert np.array_equal(result.terminated, terms[a]) and np.array_equal(result.truncated, truncs[a])
            assert np.array_equal(result.resetting, infos[a]["autoreset"])
            for key, value in infos[a].items():
                if key != "autoreset":
                    column = by_array.episode_arrays.get(key, result.outcome.info.get(key))
                    np.testing.assert_array_equal(column[:, i], value, err_msg=key)
    bad = np.zeros((W, len(agents), 3), np.float32)
    bad[1, 2, 0] = np.inf
    with pytest.raises(ValueError) as from_dict:
        by_dict.step({a: bad[:, i] for i, a in enumerate(agents)})
    with pytest.raises(ValueError) as from_array:
        by_array.step_arrays(bad)
    assert str(from_array.value) == str(from_dict.value) and "action of follower_2" in str(from_array.value)
    with pytest.raises(ValueError, match=r"expected shape \(3, 3, 3\) \(worlds, agents, action\), got \(3, 2, 3\)"):
        by_array.step_arrays(bad[:, :2])
    assert np.array_equal(by_array.simulator.t, by_dict.simulator.t)  # neither refusal stepped


def test_step_before_the_first_reset_raises_reset_needed():
    """Neither swarm env steps an episode it never started: gymnasium's ResetNeeded (also a RuntimeError, as
    the ParallelEnv raised before), saying to reset first; the vector env names the worlds never reset."""
    zeros = {"follower_0": np.zeros(3, np.float32), "follower_1": np.zeros(3, np.float32)}
    env = parallel_env(preset="stack3")
    with pytest.raises(gym_error.ResetNeeded, match=r"step\(\) before reset\(\): call reset\(\) first"):
        env.step(zeros)
    env.reset(seed=0)
    env.step(zeros)
    vec = SwarmVectorEnv(2, preset="stack3")
    both = {a: np.zeros((2, 3), np.float32) for a in vec.possible_agents}
    with pytest.raises(gym_error.ResetNeeded, match=r"world\(s\) \[0, 1\] have never been reset"):
        vec.step(both)
    vec.reset(seed=0, options={"reset_mask": np.array([False, True])})
    with pytest.raises(gym_error.ResetNeeded, match=r"world\(s\) \[0\] have never been reset"):
        vec.step(both)
    assert np.array_equal(vec.simulator.t, np.zeros(2))  # nothing stepped
    vec.reset(seed=0)
    vec.step(both)
    assert np.all(vec.simulator.t > 0.0)


# ----------------------------------------------------------------------------- rendering


def test_rendering_frames_the_swarm():
    """A fresh process (MUJOCO_GL is read at `import mujoco`); a missing EGL is a failure here."""
    code = """
        import json
        import numpy as np
        from downwash_envs.swarm import parallel_env, SwarmVectorEnv
        env = parallel_env(preset="stack3", render_mode="rgb_array", render_width=160, render_height=120)
        env.reset(seed=0)
        env.step({a: np.zeros(3, np.float32) for a in env.agents})
        f = env.render()
        r, g, b = (f[..., i].astype(int) for i in range(3))
        orange = int(((r > 150) & (g > 60) & (g < 170) & (b < 70)).sum())  # the leader
        vec = SwarmVectorEnv(2, preset="stack3", render_mode="rgb_array", render_width=160, render_height=120)
        vec.reset(seed=0)
        print(json.dumps({"shape": list(f.shape), "std": float(f.std()), "orange": orange, "n": len(vec.render())}))
    """
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=180)
    assert out.returncode == 0, out.stderr[-4000:]
    res = json.loads(out.stdout.strip().splitlines()[-1])
    assert res["shape"] == [120, 160, 3] and res["std"] > 10.0 and res["orange"] > 5 and res["n"] == 2, res
