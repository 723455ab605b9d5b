"""The Gymnasium downwash_envs: registration, API contracts, vector == sync, determinism and bit identity with the
pre-refactor code, reward terms, episode ends, the documented observation table, rendering."""

import importlib.util
import inspect
import json
import os
import subprocess
import sys
import textwrap
import warnings
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env
from gymnasium.vector import AutoresetMode, SyncVectorEnv

import downwash_envs
from downwash_core.errors import ConfigError
from downwash_core.status import Status
from downwash_envs import (
    OBS_DIM,
    REWARD_TERMS,
    DownwashFollowerEnv,
    DownwashFollowerVectorEnv,
    env_steps_per_s_single,
    env_steps_per_s_vector,
    evaluate_lqr,
)
from downwash_envs.observation import OBS_SLICES, observation_table

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
OBS = {"dp": slice(0, 3), "pos_error": slice(9, 12), "vel_error": slice(12, 15),
       "follower_z_axis": slice(21, 24), "leader_z_axis": slice(24, 27), "last_action": slice(27, 30)}
assert all(OBS_SLICES[k] == v for k, v in OBS.items())  # the documented indices are the layout's


def _run_python(code: str, env_vars: dict[str, str] | None = None, timeout: float = 180,
                unset: tuple[str, ...] = ()) -> str:
    """Run `code` in a fresh interpreter at the repo root, with `env_vars` set and the `unset`
    variables removed; returns stdout (fails with stderr)."""
    env = {k: v for k, v in {**os.environ, **(env_vars or {})}.items() if k not in unset}
    out = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=timeout)
    assert out.returncode == 0, out.stderr[-4000:]
    return out.stdout


def _same_info(a: dict, b: dict) -> None:
    assert set(a) == set(b), (sorted(a), sorted(b))
    for k in a:
        assert a[k].dtype == b[k].dtype, (k, a[k].dtype, b[k].dtype)
        assert np.array_equal(a[k], b[k]), (k, a[k], b[k])


# ----------------------------------------------------------------------------- registration


def test_every_id_is_in_the_version_history_and_old_versions_name_the_current_one():
    """docs/envs.md's version table lists every current id; an old version points to it."""
    from downwash_envs.swarm import SwarmEnv, SwarmVectorEnv

    table = (Path(__file__).resolve().parents[1] / "docs" / "envs.md").read_text().split("### Versions", 1)[1].split("\n## ", 1)[0]
    current = "| `" + table.split("\n| `", 1)[1].split("\n", 1)[0]  # the table's first row
    names = [i.split("/", 1)[1] for i in downwash_envs.ENV_IDS] + [SwarmEnv.metadata["name"]]
    for name in names:
        assert f"`{name}`" in current, (name, current)
    assert SwarmVectorEnv.metadata["name"].replace("_vector", "") == SwarmEnv.metadata["name"]
    for env_id in downwash_envs.ENV_IDS:
        namespace_name, version = env_id.rsplit("-v", 1)
        older = f"{namespace_name}-v{int(version) - 1}"
        with pytest.raises(gym.error.DeprecatedEnv, match=env_id):
            gym.make(older)


def test_import_is_light_and_module_qualified_ids_work():
    out = _run_python("""
        import json, sys
        import sim
        sim_pulls_gym = "gymnasium" in sys.modules
        import downwash_envs, gymnasium as gym
        heavy = [m for m in ("torch", "mujoco", "downwash_envs.follower") if m in sys.modules]
        print(json.dumps([sim_pulls_gym, heavy, sorted(i for i in gym.registry if i.startswith("downwash/"))]))
    """)
    sim_pulls_gym, heavy, ids = json.loads(out)
    assert not sim_pulls_gym  # `import sim` does not import gymnasium
    assert heavy == []  # registration imports gymnasium's registry only
    assert ids == sorted(downwash_envs.ENV_IDS) == ["downwash/Follower-v2", "downwash/FollowerPasses-v2"]
    for module in ("downwash_envs",):
        out = _run_python(f"""
            import sys, gymnasium as gym
            assert "{module}" not in sys.modules
            env = gym.make("{module}:downwash/Follower-v2")
            obs, _ = env.reset(seed=0)
            print(obs.shape, env.spec.max_episode_steps, type(env.unwrapped).__module__, "torch" in sys.modules)
        """)
        assert out.strip() == "(30,) 500 downwash_envs.follower False", (module, out)


def test_make_and_make_vec_give_the_documented_spaces():
    env = gym.make("downwash/Follower-v2")
    assert isinstance(env.unwrapped, DownwashFollowerEnv)
    assert env.observation_space.shape == (OBS_DIM,) == (30,)
    # float32 throughout (no check_env warning); actions normalised, the bound is physical
    assert env.observation_space.dtype == np.float32 and env.action_space.dtype == np.float32
    assert env.action_space.shape == (3,) and env.action_space.high.tolist() == [1.0] * 3
    assert env.action_space.low.tolist() == [-1.0] * 3
    assert env.unwrapped.config.bound == 5.0
    assert gym.make("downwash/Follower-v2", action_mode="acceleration").unwrapped.config.bound == 10.0
    obs, _ = env.reset(seed=0)
    assert obs.dtype == np.float32 and env.step(env.action_space.sample())[0].dtype == np.float32
    envs = gym.make_vec("downwash/Follower-v2", num_envs=2)  # the vector entry point by default
    assert isinstance(envs, DownwashFollowerVectorEnv)
    assert envs.metadata["autoreset_mode"] == AutoresetMode.NEXT_STEP
    assert envs.observation_space.shape == (2, 30) and envs.action_space.shape == (2, 3)
    assert envs.single_observation_space == env.observation_space
    assert envs.single_action_space == env.action_space
    assert envs.max_episode_steps == 500
    assert gym.spec("downwash/FollowerPasses-v2").max_episode_steps == 1000


@pytest.mark.parametrize("env_id", downwash_envs.ENV_IDS)
@pytest.mark.parametrize("mode", ["residual", "acceleration"])
def test_check_env(env_id, mode):
    env = gym.make(env_id, action_mode=mode)
    with warnings.catch_warnings():
        # physical units (m/s^2) rather than [-1, 1]: check_env's recommendation, not an error
        warnings.filterwarnings("ignore", message=".*normalized.*")
        check_env(env.unwrapped, skip_render_check=True)  # rendering: test_rendering (needs MUJOCO_GL)


# ----------------------------------------------------------------------------- vector == sync

VECTOR_CASES = {
    # vehicle collisions (world 0 pushes up into the leader), box exits, truncation; randomised field and mass
    "acceleration_hover_randomised": dict(
        action_mode="acceleration", reference="hover", separation=(0.3, 0.5),
        field_randomization="default", mass_randomization=(0.8, 1.2)),
    # per-world random passes, the oracle in the loop, a 25 Hz controller
    "residual_passes_oracle": dict(reference="passes", predictor="oracle", control_hz=25, separation=(0.4, 0.9)),
}


@pytest.mark.parametrize("case", sorted(VECTOR_CASES))
def test_vector_env_equals_sync_vector_env(case):
    """Same seeds, same actions: identical obs, rewards, terminations, truncations and infos,
    across autoresets after both termination and truncation."""
    n, horizon = 3, 25
    opts = VECTOR_CASES[case]
    vec = gym.make_vec("downwash/Follower-v2", num_envs=n, vectorization_mode="vector_entry_point",
                       max_episode_steps=horizon, **opts)
    syn = gym.make_vec("downwash/Follower-v2", num_envs=n, vectorization_mode="sync",
                       max_episode_steps=horizon, **opts)
    assert isinstance(vec, DownwashFollowerVectorEnv) and isinstance(syn, SyncVectorEnv)
    o1, i1 = vec.reset(seed=11)
    o2, i2 = syn.reset(seed=11)
    assert np.array_equal(o1, o2)
    _same_info(i1, i2)
    rng = np.random.default_rng(0)
    high = vec.single_action_space.high
    terminated = truncated = autoresets = 0
    for _ in range(45):
        a = rng.uniform(-high, high, (n, 3)).astype(np.float32)
        a[0] = [0.0, 0.0, high[2]]  # world 0 climbs (into the leader, or out of the box)
        r1, r2 = vec.step(a), syn.step(a)
        for x, y in zip(r1[:4], r2[:4]):
            assert x.dtype == y.dtype and np.array_equal(x, y)
        _same_info(r1[4], r2[4])
        autoresets += int((~r1[4].get("_status", np.ones(n, bool))).sum())
        terminated += int(r1[2].sum())
        truncated += int(r1[3].sum())
    assert terminated >= 1 and truncated >= 1 and autoresets >= 2, (terminated, truncated, autoresets)
    vec.close()
    syn.close()


def test_passes_are_drawn_per_world_within_the_separation_range():
    envs = DownwashFollowerVectorEnv(3, reference="passes", separation=(0.5, 1.2))
    _, info = envs.reset(seed=0)
    assert np.all((info["separation"] >= 0.5) & (info["separation"] <= 1.2))
    ref = envs.simulator.reference(np.full(3, 7.0)).pos[:, 1]  # follower reference at t = 7 s
    assert len({tuple(p) for p in ref}) == 3  # each world flies its own pattern
    assert np.all((2.5 - ref[:, 2] >= 0.5 - 1e-9) & (2.5 - ref[:, 2] <= 1.2 + 1e-9))


def test_vector_env_reset_mask_and_seed_list():
    envs = DownwashFollowerVectorEnv(3, max_episode_steps=50, reference="hover", separation=(0.4, 0.8))
    obs, _ = envs.reset(seed=[1, 2, 3])
    single = DownwashFollowerEnv(reference="hover", separation=(0.4, 0.8))
    assert np.array_equal(obs[1], single.reset(seed=2)[0])
    envs.step(np.zeros((3, 3), np.float32))
    before = envs.step(np.zeros((3, 3), np.float32))[0]
    obs, info = envs.reset(seed=[None, 9, None], options={"reset_mask": np.array([False, True, False])})
    assert np.array_equal(obs[[0, 2]], before[[0, 2]])
    assert np.array_equal(obs[1], single.reset(seed=9)[0])
    assert info["_separation"].tolist() == [False, True, False]
    with pytest.raises(ValueError, match="reset_mask"):
        envs.reset(options={"reset_mask": np.array([1, 0, 0])})
    with pytest.raises(ValueError, match="one per world"):
        envs.reset(seed=[1, 2])


# ----------------------------------------------------------------------------- determinism and contracts


def _rollout(env, seed, n, action_seed=0):
    rng = np.random.default_rng(action_seed)
    out = [env.reset(seed=seed)[0]]
    for _ in range(n):
        obs, reward, term, trunc, info = env.step(rng.uniform(-5, 5, 3).astype(np.float32))
        out += [obs, np.array([reward, term, trunc, info["position_error"]])]
        if term or trunc:
            out.append(env.reset()[0])
    return out


def test_same_seed_same_actions_bit_identical():
    opts = dict(reference="passes", separation=(0.5, 1.0), field_randomization="default",
                mass_randomization=(0.9, 1.1), max_episode_steps=15)
    a = _rollout(gym.make("downwash/Follower-v2", **opts), 3, 40)
    b = _rollout(gym.make("downwash/Follower-v2", **opts), 3, 40)
    assert len(a) == len(b) and all(np.array_equal(x, y) for x, y in zip(a, b))
    c = _rollout(gym.make("downwash/Follower-v2", **opts), 4, 40)
    assert not all(np.array_equal(x, y) for x, y in zip(a, c))


_spec = importlib.util.spec_from_file_location("golden_envs", Path(__file__).parent / "golden" / "env_digests.py")
golden_envs = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(golden_envs)
GOLDEN_ENVS = json.loads(golden_envs.GOLDEN.read_text())["digests"]


@pytest.mark.parametrize("case", sorted(golden_envs.CASES))
def test_envs_are_bit_identical_to_the_golden_record(case):
    """No learned model flies in these downwash_envs: the same bits on every CPU (tests/golden/env_digests.py)."""
    assert golden_envs.digest(case) == GOLDEN_ENVS[case]


@pytest.mark.parametrize("kernel", golden_envs.machine.runnable_blas_kernels())
def test_env_digests_do_not_depend_on_the_blas_kernel(kernel):
    """Under every OpenBLAS kernel this CPU can run, the envs give the recorded bits."""
    env = dict(os.environ, OPENBLAS_CORETYPE=kernel)
    proc = subprocess.run([sys.executable, str(golden_envs.__file__), "--print"], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == GOLDEN_ENVS


@pytest.mark.parametrize("masked", ["X86_V4 AVX512_ICL AVX512_SPR", "X86_V3 X86_V4 AVX512_ICL AVX512_SPR"],
                         ids=["numpy_avx2", "numpy_baseline"])
def test_env_digests_do_not_depend_on_numpys_simd_loops(masked):
    """With NumPy's AVX-512 (then also its AVX2) loops masked, as on an older CPU, the envs give the
    recorded bits: no flight takes an elementary function from NumPy's own SIMD code
    (`downwash_core.libm`). A feature this CPU lacks is ignored."""
    env = dict(os.environ, NPY_DISABLE_CPU_FEATURES=masked)
    proc = subprocess.run([sys.executable, str(golden_envs.__file__), "--print"], env=env, capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == GOLDEN_ENVS


@pytest.mark.parametrize("mode", ["residual", "acceleration"])
def test_reward_is_the_sum_of_its_terms_and_obs_stay_in_space(mode):
    env = gym.make("downwash/Follower-v2", action_mode=mode, reference="lemniscate", separation=0.4,
                   max_tracking_error=0.5, max_episode_steps=40)
    env.action_space.seed(1)
    obs, _ = env.reset(seed=1)
    ends = 0
    for _ in range(120):
        assert np.all(np.isfinite(obs)) and obs in env.observation_space
        action = env.action_space.sample()
        obs, reward, term, trunc, info = env.step(action)
        assert isinstance(reward, float) and isinstance(term, bool)
        terms = [info[f"reward_{k}"] for k in REWARD_TERMS]
        assert reward == sum(terms)  # exactly, in REWARD_TERMS order
        assert info["reward_alive"] == (0.0 if term else 1.0)
        assert info["reward_termination"] == (-50.0 if term else 0.0)
        assert info["reward_position"] == pytest.approx(-2.0 * info["position_error"])
        assert info["reward_action"] <= 0.0 and info["reward_action_rate"] <= 0.0
        # last_action: the normalised action times the bound, m/s^2 (in float32)
        bound = env.unwrapped.config.bound
        assert np.array_equal(obs[OBS["last_action"]], (action.astype(np.float64) * bound).astype(np.float32))
        assert np.linalg.norm(obs[OBS["follower_z_axis"]]) == pytest.approx(1.0)
        if term or trunc:
            ends += 1
            obs, _ = env.reset()
    assert ends >= 1


def test_reset_observation_matches_the_table():
    env = DownwashFollowerEnv(reference="hover", separation=0.7, reference_kwargs={"offset": (0.1, -0.2, 0.0)})
    obs, info = env.reset(seed=0)
    assert info == {"separation": 0.7, "mass_scale": 1.0}
    assert np.allclose(obs[OBS["dp"]], [0.1, -0.2, -0.7])  # below the leader, offset
    assert np.array_equal(obs[OBS["pos_error"]], np.zeros(3))
    assert np.array_equal(obs[OBS["follower_z_axis"]], [0.0, 0.0, 1.0])
    assert np.array_equal(obs[OBS["leader_z_axis"]], [0.0, 0.0, 1.0])
    # after a step the estimates track the truth to motion-capture accuracy
    env.step(np.zeros(3, np.float32))
    obs = env.step(np.zeros(3, np.float32))[0]
    true = env.simulator.true_states()
    assert np.allclose(obs[OBS["dp"]], true.pos[0, 1] - true.pos[0, 0], atol=5e-3)


def test_docstring_observation_table_is_the_layout():
    """The table in DownwashFollowerEnv's docstring is the one generated from downwash_envs.observation.OBSERVATION."""
    doc = inspect.getdoc(DownwashFollowerEnv)
    lines = doc.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| index |"))
    end = next(i for i in range(start, len(lines)) if not lines[i].startswith("|"))
    assert "\n".join(lines[start:end]) == observation_table()
    assert observation_table().count("\n") == 1 + len(downwash_envs.OBSERVATION)  # header, rule, one row per entry
    assert f"({OBS_DIM},)" in doc


def test_actions_reach_the_controller():
    """Residual: added to the LQR command; acceleration: replaces it; the leader keeps its LQR.
    An action is normalised: a_physical = action x bound."""
    normalised = np.array([0.1, -0.2, 0.4], np.float32)
    cmds = {}
    for mode, action in (("residual", np.zeros(3, np.float32)), ("residual", normalised),
                         ("acceleration", normalised)):
        env = DownwashFollowerEnv(action_mode=mode)
        env.reset(seed=5)
        env.step(action)
        cmds[mode, float(action[0])] = env.simulator.row["u_cmd"][0]  # (V, 3): leader, follower
    x = float(normalised[0])
    base, res, acc = cmds["residual", 0.0], cmds["residual", x], cmds["acceleration", x]
    assert np.allclose(res[1] - base[1], normalised.astype(np.float64) * 5.0, atol=1e-12)  # residual bound 5
    assert np.array_equal(acc[1], normalised.astype(np.float64) * 10.0)  # acceleration bound 10
    assert np.array_equal(res[0], base[0]) and np.array_equal(acc[0], base[0])
    # out-of-range actions are clipped to the documented bound
    env = DownwashFollowerEnv(action_mode="acceleration")
    env.reset(seed=5)
    obs = env.step(np.array([50.0, -50.0, 0.0]))[0]
    assert np.array_equal(obs[OBS["last_action"]], [10.0, -10.0, 0.0])


def test_invalid_actions_raise_before_stepping():
    env = DownwashFollowerEnv()
    env.reset(seed=0)
    t0 = env.simulator.t.copy()
    for bad in ([np.nan, 0, 0], [0, np.inf, 0], [0.0, 0.0], [[0.0, 0.0, 0.0]], "up"):
        with pytest.raises(ValueError, match="action"):
            env.step(bad)
    assert np.array_equal(env.simulator.t, t0)
    envs = DownwashFollowerVectorEnv(2)
    envs.reset(seed=0)
    for bad in (np.zeros((2, 2)), np.zeros(3), np.full((2, 3), np.nan)):
        with pytest.raises(ValueError, match="action"):
            envs.step(bad)
    assert np.array_equal(envs.simulator.t, np.zeros(2))


def test_bad_options_name_the_allowed_values():
    with pytest.raises(TypeError, match="allowed: .*separation"):
        gym.make("downwash/Follower-v2", sepration=0.5)
    # worded as Python's own, so that a wrapper probing an optional keyword retries without it, as
    # TorchRL's GymEnv does with frameskip (it looks for exactly this text)
    with pytest.raises(TypeError, match="unexpected keyword argument 'frameskip'"):
        gym.make("downwash/Follower-v2", frameskip=1)
    cases = [
        (dict(separation=0.1), "separation.*0.3"),
        (dict(separation=(0.5, 2.5)), "separation"),
        (dict(reference="circle"), "reference.*lemniscate"),
        (dict(action_mode="torque"), "action_mode.*residual"),
        (dict(control_hz=30), "control_hz.*10, 20, 25, 50, 100"),
        (dict(predictor="learned"), "predictor.*oracle"),
        (dict(predictor="oracle", action_mode="acceleration"), "predictor"),
        (dict(field_randomization={"colour": (0.9, 1.1)}), "field_randomization.*strength"),
        (dict(field_randomization={"strength": (1.2, 0.8)}), "strength"),
        (dict(mass_randomization=(0.2, 1.0)), "mass_randomization.*0.5"),
        (dict(reference_kwargs={"radius": 1.0}), "reference_kwargs.*half_length"),
        (dict(reference_kwargs={"period": -1.0}), "period"),
        (dict(reference_kwargs={"half_length": 8.0}), "allowed up to 5.0 m"),
        (dict(reference="passes", reference_kwargs={"speed_range": (0.5, 3.0)}), "speed_range"),
        (dict(leader_position=(0.0, 0.0, 0.5)), "leader_position"),
        (dict(c4_amplitude=2.0), "c4_amplitude"),
        (dict(max_tracking_error=0.0), "max_tracking_error"),
        (dict(swirl=0.5, field=lambda p_a, v_a, R_a, p_b, v_b: np.zeros(np.broadcast_shapes(p_a.shape, p_b.shape))),
         "DownwashField"),
        (dict(field=lambda *a: 0.0), r"field: expected accelerations of shape \(\.\.\., 3\)"),
        (dict(field=lambda p_a, v_a, R_a, p_b, v_b: np.full(np.broadcast_shapes(p_a.shape, p_b.shape), np.nan)),
         "field: returned non-finite accelerations"),
    ]
    for opts, match in cases:
        with pytest.raises(ValueError, match=match):
            DownwashFollowerEnv(**opts)
    with pytest.raises(ValueError, match="reset options"):
        DownwashFollowerEnv().reset(seed=0, options={"separation": 1.0})
    with pytest.raises(ValueError, match="render_mode.*rgb_array.*human"):
        DownwashFollowerEnv(render_mode="bogus")
    with pytest.raises(ValueError, match="num_envs"):
        DownwashFollowerVectorEnv(0)
    with pytest.raises(ValueError, match="max_episode_steps"):
        DownwashFollowerVectorEnv(2, max_episode_steps=0)
    with pytest.raises(TypeError, match="allowed: .*control_hz"):
        DownwashFollowerVectorEnv(2, controlhz=25)


# ----------------------------------------------------------------------------- episode ends


# Each numeric option given as a string or a bool: float() reads "0.6" as 0.6 and True as 1.0, so each
# of these was accepted; every one now names the option and its allowed range.
_TEXT_OR_BOOL = [
    (dict(separation="0.6"), r"separation: expected a number, got '0.6' \(a str.*allowed .*\[0.3, 2.0\] m"),
    (dict(separation=True), r"separation: expected a number, got True \(a bool.*allowed .*\[0.3, 2.0\] m"),
    (dict(separation=np.bool_(True)), r"separation: expected a number.*a bool"),
    (dict(separation=(0.5, "1.0")), r"separation: .*'1.0' is a str.*allowed"),
    (dict(separation=(True, 1.0)), r"separation: .*True is a bool.*allowed"),
    (dict(action_bound="5"), r"action_bound: expected a number.*allowed \(0.0, 20.0\] m/s\^2"),
    (dict(action_bound=True), r"action_bound: expected a number.*allowed \(0.0, 20.0\] m/s\^2"),
    (dict(leader_position=("0", "0", "2")), r"leader_position: expected a number.*allowed \(x, y, z\) m, z in"),
    (dict(leader_position=(0.0, False, 2.0)), r"leader_position: .*False is a bool"),
    (dict(c4_amplitude=False), r"c4_amplitude: expected a number.*allowed \[-0.99, 0.99\]"),
    (dict(swirl="0.1"), r"swirl: expected a number.*allowed \[-10.0, 10.0\]"),
    (dict(skew=False), r"skew: expected a number.*allowed \[0.0, 10.0\] s/m"),
    (dict(max_tracking_error="1"), r"max_tracking_error: expected a number.*allowed \(0.0, 5.0\] m"),
    *((dict([(w, True)]), rf"{w}: expected a number.*allowed \[0.0, 1000000.0\]") for w in (
        "alive_reward", "position_cost_weight", "velocity_cost_weight", "action_cost_weight",
        "action_rate_cost_weight", "termination_penalty")),
    (dict(mass_randomization=("0.9", 1.1)), r"mass_randomization: .*allowed \(low, high\) with 0.5 <= low"),
    (dict(field_randomization={"strength": (True, 1.2)}), r"field_randomization\['strength'\]: .*bool.*0.1 <= low"),
    (dict(reference_kwargs={"half_length": "1.0"}), r"reference_kwargs\['half_length'\]: expected a number"),
    (dict(reference_kwargs={"period": True}), r"reference_kwargs\['period'\]: expected a number.*a bool"),
    (dict(reference="transect", reference_kwargs={"x_offset": False}), r"reference_kwargs\['x_offset'\]"),
    (dict(reference="hover", reference_kwargs={"offset": ("0.1", 0.0, 0.0)}), r"reference_kwargs\['offset'\]"),
    (dict(reference="passes", reference_kwargs={"duration": "10"}), r"reference_kwargs\['duration'\]"),
    (dict(reference="passes", reference_kwargs={"speed_range": ("0.5", 1.0)}), r"reference_kwargs\['speed_range'\]"),
    (dict(reference="passes", reference_kwargs={"hover_prob": True}), r"reference_kwargs\['hover_prob'\]"),
]  # fmt: skip


@pytest.mark.parametrize("opts, match", _TEXT_OR_BOOL, ids=[repr(opts) for opts, _ in _TEXT_OR_BOOL])
def test_numeric_options_refuse_strings_and_bools(opts, match):
    with pytest.raises(ConfigError, match=match):
        DownwashFollowerEnv(**opts)
    with pytest.raises(ConfigError, match=match):
        DownwashFollowerVectorEnv(2, **opts)


def test_numeric_options_still_take_numpy_numbers():
    """The string/bool refusal leaves numpy scalars and arrays alone (they fly as before)."""
    env = DownwashFollowerEnv(separation=np.float64(0.7), action_bound=np.float32(4.0),
                              leader_position=np.array([0.0, 0.0, 2.0]), reference="hover")
    assert env.config.separation_range == (0.7, 0.7) and env.config.bound == 4.0
    env = gym.make("downwash/FollowerPasses-v2", separation=np.array([0.5, 1.0]))
    assert env.unwrapped.config.separation_range == (0.5, 1.0)
    with pytest.raises(ConfigError, match="separation: expected a number, got '0.6'"):
        gym.make("downwash/Follower-v2", separation="0.6")


def test_step_before_the_first_reset_raises_reset_needed():
    """An env made directly (no gym.make, so no OrderEnforcing wrapper) refuses to step an episode it never
    started, rather than flying the placeholder state it was built with; nothing is stepped."""
    env = DownwashFollowerEnv(reference="hover")
    with pytest.raises(gym.error.ResetNeeded, match=r"step\(\) before reset\(\): call reset\(\) first"):
        env.step(np.zeros(3, np.float32))
    assert np.array_equal(env.simulator.t, np.zeros(1))
    env.reset(seed=0)
    env.step(np.zeros(3, np.float32))
    assert env.simulator.t[0] > 0.0
    envs = DownwashFollowerVectorEnv(3, reference="hover")
    with pytest.raises(gym.error.ResetNeeded, match=r"world\(s\) \[0, 1, 2\] have never been reset"):
        envs.step(np.zeros((3, 3), np.float32))
    envs.reset(seed=0, options={"reset_mask": np.array([True, False, True])})
    with pytest.raises(gym.error.ResetNeeded, match=r"world\(s\) \[1\] have never been reset.*reset_mask"):
        envs.step(np.zeros((3, 3), np.float32))
    assert np.array_equal(envs.simulator.t, np.zeros(3))
    envs.reset(seed=0, options={"reset_mask": np.array([False, True, False])})
    envs.step(np.zeros((3, 3), np.float32))
    assert np.all(envs.simulator.t > 0.0)
    vec = gym.make_vec("downwash/Follower-v2", num_envs=2, reference="hover")  # the native env, unwrapped
    with pytest.raises(gym.error.ResetNeeded):
        vec.step(np.zeros((2, 3), np.float32))


@pytest.mark.parametrize("push, status", [((0.0, 0.0, 10.0), Status.VEHICLE), ((0.0, 0.0, -10.0), Status.GROUND),
                                          ((10.0, 0.0, 0.0), Status.LEFT_BOX)])
def test_termination_on_collision_and_leaving_the_box(push, status):
    box = 1.0 if status == Status.LEFT_BOX else 5.0
    env = gym.make("downwash/Follower-v2", action_mode="acceleration", reference="hover", separation=0.4,
                   max_tracking_error=box)
    env.reset(seed=0)
    for _ in range(150):
        _, reward, term, trunc, info = env.step(np.array(push, np.float32))
        if term or trunc:
            break
    assert term and not trunc and info["status"] == status
    assert info["reward_termination"] == -50.0 and info["reward_alive"] == 0.0


def test_truncation_at_the_horizon_and_next_step_autoreset():
    env = gym.make("downwash/Follower-v2", max_episode_steps=5)
    env.reset(seed=0)
    truncs = [env.step(np.zeros(3, np.float32))[3] for _ in range(5)]
    assert truncs == [False] * 4 + [True]
    envs = gym.make_vec("downwash/Follower-v2", num_envs=2, max_episode_steps=5)
    first, _ = envs.reset(seed=0)
    for k in range(5):
        obs, rew, term, trunc, info = envs.step(np.zeros((2, 3), np.float32))
        assert trunc.tolist() == [k == 4] * 2 and not term.any()
    obs, rew, term, trunc, info = envs.step(np.ones((2, 3), np.float32))  # ignored: autoreset
    assert rew.tolist() == [0.0, 0.0] and "status" not in info and info["_separation"].all()
    assert not np.array_equal(obs, first)  # a new episode (the generators moved on)
    assert np.array_equal(envs.simulator.t, np.zeros(2))


# ----------------------------------------------------------------------------- options


def test_control_rate_option():
    env = DownwashFollowerEnv(control_hz=25)
    env.reset(seed=0)
    env.step(np.zeros(3, np.float32))
    assert env.dt == pytest.approx(0.04) and env.simulator.t[0] == pytest.approx(0.04)
    assert env.metadata["render_fps"] == 25
    assert env.simulator.cfg.rates.physics_per_control == 20


def test_domain_randomisation_is_per_world_and_the_controller_keeps_nominal_mass():
    envs = DownwashFollowerVectorEnv(3, field_randomization={"strength": (0.5, 1.5)}, mass_randomization=(0.6, 1.4))
    _, info = envs.reset(seed=0)
    s = envs.simulator
    strength = s.field.strength.reshape(-1)
    assert np.allclose(strength, 10.6 * info["field_scale_strength"]) and len(set(strength)) == 3
    body = s.scene.body_ids[1]
    masses = s.physics.batch.expand("body_mass")[:, body]
    assert np.allclose(masses, 0.7 * info["mass_scale"]) and len(set(masses)) == 3
    assert np.array_equal(s._mass_believed, np.full((3, 2), 0.7))
    # leader mass untouched
    assert np.allclose(s.physics.batch.expand("body_mass")[:, s.scene.body_ids[0]], 0.7)


def test_evaluate_lqr_oracle_beats_baseline():
    """The oracle in the loop (predictor='oracle') cancels the wake: smaller tracking error."""
    opts = dict(reference="hover", separation=0.5, num_envs=2, n_steps=100, seed=0)
    base, oracle = evaluate_lqr(False, **opts), evaluate_lqr(True, **opts)
    assert base["terminated"] == oracle["terminated"] == 0 and base["env_steps"] == 200
    assert oracle["pos_err_3d_mean"] < 0.7 * base["pos_err_3d_mean"], (oracle, base)


def test_benchmark_helpers_run():
    assert env_steps_per_s_single(20, repeats=1) > 0
    assert env_steps_per_s_vector(num_envs=2, n_steps=5, repeats=1) > 0


# ----------------------------------------------------------------------------- rendering


def test_rendering_gives_a_frame_with_both_vehicles():
    """Offscreen rendering through MuJoCo's EGL backend (a fresh process: MUJOCO_GL is read at
    `import mujoco`). Needs libEGL and Mesa (see README); a missing backend is a failure here."""
    out = _run_python("""
        import json, warnings
        import numpy as np, gymnasium as gym
        from gymnasium.utils.env_checker import check_env
        import downwash_envs
        env = gym.make("downwash/Follower-v2", render_mode="rgb_array", reference="transect", random_phase=False)
        env.reset(seed=0)
        for _ in range(5):
            env.step(np.zeros(3, np.float32))
        f = env.render()
        r, g, b = (f[..., i].astype(int) for i in range(3))
        orange = int(((r > 150) & (g > 60) & (g < 170) & (b < 70)).sum())  # leader hull
        cyan = int(((r < 80) & (g > 120) & (b > 130)).sum())  # follower hull
        envs = gym.make_vec("downwash/Follower-v2", num_envs=2, render_mode="rgb_array")
        envs.reset(seed=0)
        frames = envs.render()
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            # gymnasium's render checks, for rgb_array ("human" needs a display: tests/test_viewer.py)
            from gymnasium.utils.passive_env_checker import env_render_passive_checker
            rgb = gym.make("downwash/Follower-v2", render_mode="rgb_array").unwrapped
            check_env(rgb, skip_render_check=True)
            rgb.reset(seed=0)
            env_render_passive_checker(rgb)
        print(json.dumps({"shape": list(f.shape), "dtype": str(f.dtype), "std": float(f.std()),
                          "orange": orange, "cyan": cyan, "n_frames": len(frames),
                          "frame_shape": list(frames[1].shape)}))
    """, env_vars={"MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")})
    res = json.loads(out.strip().splitlines()[-1])
    assert res["shape"] == [360, 480, 3] and res["dtype"] == "uint8"
    assert res["std"] > 10.0  # not blank
    assert res["orange"] > 20 and res["cyan"] > 20, res
    assert res["n_frames"] == 2 and res["frame_shape"] == [360, 480, 3]


def test_rendering_chooses_egl_on_a_headless_machine():
    """With MUJOCO_GL, DISPLAY and WAYLAND_DISPLAY unset, render() works without any setting:
    EGL is chosen even though mujoco (imported first) has already read MUJOCO_GL."""
    out = _run_python("""
        import json, os
        import mujoco  # reads MUJOCO_GL (unset) now
        import numpy as np
        from downwash_envs import DownwashFollowerEnv
        env = DownwashFollowerEnv(render_mode="rgb_array", render_width=160, render_height=120)
        env.reset(seed=0)
        env.step(np.zeros(3, np.float32))
        f = env.render()
        env.close()
        print(json.dumps({"gl": os.environ.get("MUJOCO_GL"), "shape": list(f.shape), "std": float(f.std())}))
    """, unset=("MUJOCO_GL", "DISPLAY", "WAYLAND_DISPLAY"))
    res = json.loads(out.strip().splitlines()[-1])
    assert res["gl"] == "egl" and res["shape"] == [120, 160, 3]
    assert res["std"] > 10.0  # not blank


def test_rendering_without_a_backend_names_mujoco_gl():
    out = _run_python("""
        import numpy as np
        from downwash_envs import DownwashFollowerEnv
        env = DownwashFollowerEnv(render_mode="rgb_array")
        env.reset(seed=0)
        try:
            env.render()
        except RuntimeError as e:
            print("RuntimeError", e)
    """, env_vars={"MUJOCO_GL": "disable"})
    assert out.startswith("RuntimeError") and "MUJOCO_GL" in out and "egl" in out and "osmesa" in out
    with pytest.warns(UserWarning, match="render_mode"):
        assert DownwashFollowerEnv().render() is None  # no render_mode: a warning, no frame


def test_lqr_and_turbulence_options_reach_the_simulator():
    """The component options change the flight: no turbulence, or softer position weights."""
    from controllers.lqr import LQRConfig
    from sim.turbulence import OUTurbulence

    def run(**options):
        env = DownwashFollowerEnv(**options)
        env.reset(seed=3)
        for _ in range(60):
            obs, *_ = env.step(np.zeros(3, np.float32))
        assert env.simulator.turbulence == options.get("turbulence", OUTurbulence())
        return obs

    base = run()
    assert not np.array_equal(base, run(turbulence=OUTurbulence(intensity=0.0)))
    assert not np.array_equal(base, run(lqr=LQRConfig(q=(0.2, 0.2, 2.0, 0.01, 0.01, 0.1, 1.0))))
    with pytest.raises(ValueError, match="turbulence: expected a sim.turbulence.OUTurbulence"):
        DownwashFollowerEnv(turbulence=0.1)


@pytest.mark.parametrize("seed", range(3))
def test_compiled_observation_equals_the_readable_one(seed):
    """`FollowerWorlds`' compiled observation against `downwash_envs.task.observation`, bit for bit: random
    states (leader and follower in either scene slot), entries beyond their bounds, a diverged
    (NaN) world; and each entry where OBS_SLICES puts it."""
    from downwash_envs.observation import obs_bounds
    from downwash_envs.task import observe_kernel, observation
    from downwash_trajectories import RefSample

    rng = np.random.default_rng(seed)
    W, V = 5, 3
    pos, vel = rng.normal(scale=4, size=(W, V, 3)), rng.normal(scale=15, size=(W, V, 3))
    rot = np.linalg.qr(rng.normal(size=(W, V, 3, 3)))[0]
    ref = RefSample(rng.normal(size=(W, V, 3)), rng.normal(size=(W, V, 3)), rng.normal(scale=20, size=(W, V, 3)),
                    np.zeros((W, V)), np.zeros((W, V)))
    leader, follower = (2, 0) if seed % 2 else (0, 2)
    pos[3, :] = np.nan
    vel[1, follower] = [30.0, -30.0, 0.0]  # beyond the bound of 20 m/s, both ways
    last = rng.uniform(-5, 5, (W, 3))
    low, high = obs_bounds(5.0)
    want = observation(pos, vel, rot, ref, leader, follower, last, low, high)
    got = np.empty_like(want)
    observe_kernel(pos, vel, rot, ref.pos, ref.vel, ref.acc, leader, follower, last, low, high, got)
    np.testing.assert_array_equal(got, want)
    assert (want == low).any() and (want == high).any() and np.isfinite(want).all()
    assert np.all(want[3, OBS_SLICES["dp"]] == 0.0)  # the diverged world's NaN reads 0
    w = 0
    np.testing.assert_array_equal(want[w, OBS_SLICES["v_leader"]], np.clip(vel[w, leader], -20, 20))
    np.testing.assert_array_equal(want[w, OBS_SLICES["leader_z_axis"]], rot[w, leader, :, 2])
    np.testing.assert_array_equal(want[w, OBS_SLICES["last_action"]], last[w])


def test_actions_are_clipped_as_numpy_clips_and_bad_ones_refused_before_stepping():
    env = gym.make("downwash/Follower-v2").unwrapped
    env.reset(seed=0)
    worlds = env._worlds
    a = np.array([7.5, -0.0, -12.0], np.float32)
    np.testing.assert_array_equal(worlds.check_actions(a, (3,)), np.clip(a.astype(np.float64), -5.0, 5.0))
    t = env.simulator.t.copy()
    for bad in ([0.0, np.nan, 0.0], [np.inf, 0.0, 0.0]):
        with pytest.raises(ValueError, match="must be finite"):
            env.step(np.array(bad, np.float32))
    assert np.array_equal(env.simulator.t, t)  # nothing stepped


class _Push:
    """A predictor object with state: a constant push, counting the calls and resets it is told of."""

    stateful = True

    def __init__(self):
        self.calls, self.resets = 0, []

    def reset(self, worlds=None):
        self.resets.append(None if worlds is None else list(np.asarray(worlds)))

    def __call__(self, estimated, true, due=None):
        self.calls += 1
        out = np.zeros_like(estimated.pos)
        out[..., 2] = -0.5
        return out


def test_a_predictor_object_flies_as_each_envs_own_copy():
    """predictor=<object>: each env flies its own copy (a predictor with state serves one simulator), reset
    with the env's worlds; the LQR subtracts what it predicts. A guarded learned model runs the same way."""
    given = _Push()
    env = DownwashFollowerEnv(reference="hover", separation=0.6, predictor=given)
    env.reset(seed=0)
    env.step(np.zeros(3))
    own = env._worlds.sim.predictor
    assert isinstance(own, _Push) and own is not given and given.calls == 0 and own.calls >= 1
    assert own.resets and env._worlds.sim.f_hat[0, 1, 2] == -0.5
    from downwash.checkpoint import wrap_pairwise
    from downwash.guard import GuardedPredictor, support_of
    from downwash.predictor import LearnedPredictor
    from downwash.registry import make_model

    rng = np.random.default_rng(0)
    dp = np.column_stack([rng.uniform(-0.3, 0.3, (500, 2)), -rng.uniform(0.4, 0.9, 500)])
    support = support_of(dp, rng.normal(size=(500, 3)) * 0.05, rng.normal(size=(500, 3)) * 0.3,
                         np.broadcast_to(np.eye(3), (500, 3, 3)))  # a hovering leader, its estimate noisy
    guard = GuardedPredictor(LearnedPredictor(wrap_pairwise(make_model("equivariant").double().eval())), support,
                             prior=1e12, fast_prior=1e12)  # (its monitor trusts the untrained model: the
    # support alone acts)
    env = DownwashFollowerEnv(reference="hover", separation=0.6, predictor=guard)
    env.reset(seed=1)
    for _ in range(20):
        env.step(np.zeros(3))
    assert env._worlds.sim.predictor.applied[0, 1] > 0.9 and guard.applied is None  # its copy flew, inside the support
    assert env._worlds.sim.predictor._seen_t[0] > 0 and guard._seen is None  # and its copy watched the flight
    with pytest.raises(Exception, match="predictor"):
        DownwashFollowerEnv(predictor=object())
    with pytest.raises(Exception, match="predictor"):
        DownwashFollowerEnv(predictor=_Push(), action_mode="acceleration")
