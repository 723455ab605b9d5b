"""Per-episode vehicle randomisation on request (the `randomize` option): off by default and then
the envs fly as before (the golden digests in test_env.py hold that bit for bit); on, each episode
draws the agents' mass, inertia and motor lag from the env's seeded generator, the worlds' MuJoCo
models carry them, the flights change, and the draws repeat for a seed."""

import dataclasses
import json

import numpy as np
import pytest

from downwash_core.errors import ConfigError
from downwash_envs.config import FollowerConfig
from downwash_envs.engine import VehicleModel
from downwash_envs.follower import DownwashFollowerEnv, DownwashFollowerVectorEnv
from downwash_envs.task import _scene

ALL = {"mass": 0.3, "inertia": 0.4, "motor_lag": 0.5}
OPTS = dict(reference="hover", separation=0.6)


def _rollout(env, seed, n=25):
    obs, info = env.reset(seed=seed)
    out = [obs]
    for k in range(n):
        obs, reward, *_ = env.step(np.full(3, 0.4 * np.sin(k), np.float32))
        out += [obs, np.asarray(reward)]
    return info, out


def _equal(a, b):
    return len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))


def test_off_by_default():
    assert FollowerConfig().randomize is None and FollowerConfig().vehicle_spreads == {}
    _, default = _rollout(DownwashFollowerEnv(**OPTS), 3)
    _, empty = _rollout(DownwashFollowerEnv(randomize={}, **OPTS), 3)
    assert _equal(default, empty)


@pytest.mark.parametrize("parameter", ["mass", "inertia", "motor_lag"])
def test_each_parameter_changes_the_flight_and_nothing_else_drawn(parameter):
    """The factors are drawn after every other draw: the same episode (reference, noise seed),
    the same start, a different flight."""
    info0, off = _rollout(DownwashFollowerEnv(**OPTS), 5)
    info1, on = _rollout(DownwashFollowerEnv(randomize={parameter: 0.5}, **OPTS), 5)
    assert info1["separation"] == info0["separation"]
    assert np.array_equal(on[0], off[0])  # the reset state
    assert not _equal(on, off)
    scale = info1["mass_scale"] if parameter == "mass" else info1[f"{parameter}_scale"]
    assert 0.5 <= scale <= 1.5 and scale != 1.0


def test_the_models_carry_the_draws_and_the_controller_keeps_nominal():
    envs = DownwashFollowerVectorEnv(3, randomize=ALL, **OPTS)
    _, info = envs.reset(seed=0)
    sim, scene = envs.simulator, envs.simulator.scene
    leader, follower = scene.body_ids[scene.leader], scene.body_ids[scene.follower]
    model = scene.model  # the nominal model, shared and untouched
    batch = sim.physics.batch
    mass, inertia = batch.expand("body_mass"), batch.expand("body_inertia")
    np.testing.assert_allclose(mass[:, follower], 0.7 * info["mass_scale"], rtol=1e-12)
    np.testing.assert_allclose(inertia[:, follower], model.body_inertia[follower]
                               * (info["mass_scale"] * info["inertia_scale"])[:, None], rtol=1e-12)
    lag = batch.expand("actuator_dynprm")[:, scene.act_ids[scene.follower], 0]
    np.testing.assert_allclose(lag, 0.03 * np.repeat(info["motor_lag_scale"][:, None], 4, axis=1), rtol=1e-12)
    assert len(set(info["motor_lag_scale"])) == 3  # one draw per world
    assert np.all(mass[:, leader] == 0.7)
    assert np.all(batch.expand("actuator_dynprm")[:, scene.act_ids[scene.leader], 0] == 0.03)
    assert np.all(model.body_mass[[leader, follower]] == 0.7) and np.all(model.actuator_dynprm[:, 0] == 0.03)
    assert np.array_equal(sim._mass_believed, np.full((3, 2), 0.7))
    # the next episodes draw again, and their factors replace the last ones (not compounded)
    envs.reset(seed=1)
    _, again = envs.reset(seed=0)
    assert all(np.array_equal(again[k], info[k]) for k in ("mass_scale", "inertia_scale", "motor_lag_scale"))
    np.testing.assert_allclose(inertia[:, follower], model.body_inertia[follower]
                               * (info["mass_scale"] * info["inertia_scale"])[:, None], rtol=1e-12)


def test_single_world_model_carries_the_draws():
    env = DownwashFollowerEnv(randomize=ALL, **OPTS)
    _, info = env.reset(seed=2)
    physics, scene = env.simulator.physics, env.simulator.scene
    follower = scene.body_ids[scene.follower]
    assert physics.model is not scene.model  # its own copy, the shared one untouched
    assert physics.model.body_mass[follower] == pytest.approx(0.7 * info["mass_scale"], rel=1e-12)
    np.testing.assert_allclose(physics.model.actuator_dynprm[scene.act_ids[scene.follower], 0],
                               0.03 * info["motor_lag_scale"], rtol=1e-12)
    assert scene.model.body_mass[follower] == 0.7 and np.all(scene.model.actuator_dynprm[:, 0] == 0.03)


def test_draws_repeat_for_a_seed_and_the_vector_env_equals_single_envs():
    """World i of the vector env (its own model in a batch) flies as the single env seeded s + i
    (its model copy), bit for bit; the same seed gives the same draws and flight."""
    a_info, a = _rollout(DownwashFollowerEnv(randomize=ALL, **OPTS), 7)
    b_info, b = _rollout(DownwashFollowerEnv(randomize=ALL, **OPTS), 7)
    assert a_info == b_info and _equal(a, b)
    c_info, _ = _rollout(DownwashFollowerEnv(randomize=ALL, **OPTS), 8)
    assert c_info["motor_lag_scale"] != a_info["motor_lag_scale"]

    envs = DownwashFollowerVectorEnv(2, randomize=ALL, **OPTS)
    obs, info = envs.reset(seed=7)
    singles = [DownwashFollowerEnv(randomize=ALL, **OPTS) for _ in range(2)]
    first = [env.reset(seed=7 + i) for i, env in enumerate(singles)]
    for i, (o, inf) in enumerate(first):
        assert np.array_equal(obs[i], o) and info["inertia_scale"][i] == inf["inertia_scale"]
    for k in range(20):
        action = np.full((2, 3), 0.4 * np.sin(k), np.float32)
        obs, reward, *_ = envs.step(action)
        for i, env in enumerate(singles):
            o, r, *_ = env.step(action[i])
            assert np.array_equal(obs[i], o) and reward[i] == r


@pytest.mark.parametrize("value, match", [
    ({"mass": 0.7}, r"randomize\['mass'\]: got 0.7; allowed \[0.0, 0.5\]"),
    ({"motor_lag": -0.1}, r"randomize\['motor_lag'\]: got -0.1; allowed \[0.0, 0.5\]"),
    ({"inertia": "a lot"}, r"randomize\['inertia'\]: expected a number"),
    ({"mass": "0.1"}, r"randomize\['mass'\]: expected a number, got '0.1' \(a str.*allowed \[0.0, 0.5\]"),
    ({"motor_lag": False}, r"randomize\['motor_lag'\]: expected a number, got False \(a bool.*allowed \[0.0, 0.5\]"),
    ({"drag": 0.1}, r"randomize: unknown parameter\(s\) \['drag'\]; allowed: mass, inertia, motor_lag"),
    (0.1, r"randomize: expected None or a dict"),
])  # fmt: skip
def test_bad_values_name_the_option_and_the_allowed_range(value, match):
    with pytest.raises(ValueError, match=match):
        DownwashFollowerEnv(randomize=value)
    with pytest.raises(ConfigError, match=match):
        DownwashFollowerVectorEnv(2, randomize=value)


def test_not_with_mass_randomization_and_motor_lag_stays_above_the_physics_step():
    with pytest.raises(ConfigError, match="randomize and mass_randomization: give one"):
        DownwashFollowerEnv(randomize={"mass": 0.1}, mass_randomization=(0.9, 1.1))
    scene = _scene()
    model = scene.model.__copy__()
    model.opt.timestep = 0.02  # a motor lag of 0.03 s at half would be below it
    coarse = dataclasses.replace(scene, model=model)
    too_coarse = r"randomize\['motor_lag'\]: got 0.5.*physics step 0.02 s.*allowed \[0, 0.333\)"
    with pytest.raises(ConfigError, match=too_coarse):
        VehicleModel(coarse, np.array([scene.follower]), {"motor_lag": 0.5})
    VehicleModel(coarse, np.array([scene.follower]), {"motor_lag": 0.3})


def test_swarm_randomizes_every_follower_and_the_vector_env_equals_the_parallel_env():
    from downwash_envs.swarm import SwarmVectorEnv, make_swarm_config, parallel_env

    opts = dict(preset="stack3", randomize={"mass": 0.2, "motor_lag": 0.4})
    vec = SwarmVectorEnv(2, **opts)
    obs, infos = vec.reset(seed=4)
    agents = vec.agents
    scales = np.stack([infos[a]["mass_scale"] for a in agents], axis=1)  # (W, A)
    assert len(set(scales.ravel())) == scales.size and "inertia_scale" not in infos[agents[0]]
    sim = vec.simulator
    bodies = sim.scene.body_ids[vec._worlds.agent_index]
    np.testing.assert_allclose(sim.physics.batch.expand("body_mass")[:, bodies], 0.7 * scales, rtol=1e-12)
    assert np.all(sim.physics.batch.expand("body_mass")[:, sim.scene.body_ids[sim.scene.leader]] == 0.7)
    envs = [parallel_env(**opts) for _ in range(2)]
    first = [env.reset(seed=4 + k) for k, env in enumerate(envs)]
    for k, (o, inf) in enumerate(first):
        for a in agents:
            assert np.array_equal(obs[a][k], o[a]) and infos[a]["motor_lag_scale"][k] == inf[a]["motor_lag_scale"]
    for step in range(15):
        actions = {a: np.full((2, 3), 0.3 * np.cos(step + i), np.float32) for i, a in enumerate(agents)}
        obs, rewards, *_ = vec.step(actions)
        for k, env in enumerate(envs):
            o, r, *_ = env.step({a: actions[a][k] for a in agents})
            assert all(np.array_equal(obs[a][k], o[a]) and rewards[a][k] == r[a] for a in agents)
    # provenance names the option only when it is on (the records written before it stay valid)
    assert "randomize" not in make_swarm_config(preset="stack3").describe()
    assert json.dumps(make_swarm_config(**opts).describe()["randomize"]) == '{"mass": 0.2, "motor_lag": 0.4}'
