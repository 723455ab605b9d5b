"""The envs fly the non-learned baselines and the lab controllers: predictor="dob" (a disturbance observer)
and controller="integral" | "mellinger" | "pid" | "indi", each checked against what it must do."""

import gymnasium as gym
import numpy as np
import pytest

import downwash_envs  # noqa: F401  (registers the ids)
from controllers.lqr import LQRConfig
from downwash_core.errors import ConfigError

HOVER = {"reference": "hover", "separation": 0.6, "random_phase": False}


def _mean_error(steps=150, **options):
    """The follower's mean position error (m) over the second half of a zero-action hover below the leader."""
    env = gym.make("downwash/Follower-v2", **options)
    env.reset(seed=3)
    errors = []
    for _ in range(steps):
        _, _, term, trunc, info = env.step(np.zeros(3, dtype=np.float32))
        assert not term, info
        errors.append(info["position_error"])
    env.close()
    return float(np.mean(errors[steps // 2:]))


def test_the_observer_and_integral_action_remove_most_of_the_wakes_sag():
    """Under the leader's wake the plain LQR sags; the observer's estimate (as the compensation) and the
    integral action both remove most of it, with no learned model."""
    plain = _mean_error(**HOVER)
    observed = _mean_error(predictor="dob", **HOVER)
    integral = _mean_error(controller="integral", **HOVER)
    assert plain > 0.05  # the wake's push over the LQR's stiffness: a sag of centimetres
    assert observed < 0.5 * plain and integral < 0.5 * plain, (plain, observed, integral)


@pytest.mark.parametrize("name", ["mellinger", "pid", "indi"])
def test_the_lab_controllers_fly_the_env(name):
    assert _mean_error(steps=100, controller=name, **HOVER) < 0.3


def test_the_swarm_env_takes_the_controller_and_the_observer():
    from downwash_envs.swarm import SwarmVectorEnv

    env = SwarmVectorEnv(2, preset="stack3", controller="integral", predictor="dob")
    env.reset(seed=0)
    actions = {a: np.zeros((2, 3), dtype=np.float32) for a in env.agents}
    for _ in range(20):
        env.step(actions)
    sim = env._worlds.sim  # (the batched simulator the env steps)
    assert type(sim.controller).__name__ == "IntegralLQR" and type(sim.predictor).__name__ == "DisturbanceObserver"
    assert sim.controller.describe()["dt"] == pytest.approx(1.0 / 50)  # at the env's control rate
    env.close()


@pytest.mark.parametrize("options, words", [
    ({"controller": "lqg"}, "controller: got 'lqg'"),
    ({"controller": "pid", "lqr": LQRConfig()}, "controller='pid' has its own gains"),
    ({"predictor": "dob", "action_mode": "acceleration"}, "only acts on the LQR command"),
])
def test_bad_choices_are_refused_naming_what_is_allowed(options, words):
    with pytest.raises(ConfigError, match=words):
        gym.make("downwash/Follower-v2", **options)
