"""Gymnasium environments: a follower quadrotor in a hovering leader's downwash.

The leader ("alpha") hovers; the follower ("bravo") tracks a reference below it,
through or beside the leader's wake, flying the full stack of `sim.simulator`
(motors, autopilot, Kalman-filtered motion capture, 500 Hz physics, the
ground-truth downwash field with turbulence). The agent commands the follower's
acceleration once per controller period.

Two classes, one engine:

- `DownwashFollowerEnv`: a `gymnasium.Env` (one world, plain `MjData`).
- `DownwashFollowerVectorEnv`: a native `gymnasium.vector.VectorEnv` whose worlds
  share one `mujoco.batch.Batch` (next-step autoreset, Gymnasium 1.x's default).
  Step for step it equals `gymnasium.vector.SyncVectorEnv` of single envs made
  with the same options and seeds (world i of `reset(seed=s)` uses seed s + i).

Both run `_FollowerWorlds`, which holds per-world episode parameters (reference,
separation, field constants, mass) and evaluates everything batched over worlds;
Python loops over worlds happen only at reset.

Registered ids (`import sim`, or `gymnasium.make("sim:DownwashFollower-v0")`):

- ``DownwashFollower-v0``: the paper's lemniscate beneath the leader, 0.6 m below
  it, 500 steps (10 s at 50 Hz).
- ``DownwashFollowerPasses-v0``: randomised passes and hovers through and beside
  the wake (the staged data collection's patterns), 0.5-1.2 m below, 1000 steps.

Every option of `FollowerConfig` is a `make` keyword; `action_mode` is
``"residual"`` (default) or ``"acceleration"``. Example::

    import gymnasium as gym
    import sim  # registers the ids

    env = gym.make("DownwashFollower-v0", action_mode="residual", separation=0.5)
    obs, info = env.reset(seed=0)
    for _ in range(500):
        action = env.action_space.sample()  # (3,) m/s^2, added to the LQR command
        obs, reward, terminated, truncated, info = env.step(action)
        if terminated or truncated:
            obs, info = env.reset()

    envs = gym.make_vec("DownwashFollower-v0", num_envs=64)  # native batched env
    obs, infos = envs.reset(seed=0)                            # (64, 30)
    obs, rewards, terminations, truncations, infos = envs.step(envs.action_space.sample())

The built-in LQR with and without the oracle (action 0 in residual mode; the
oracle is the env option ``predictor="oracle"``)::

    from sim.env import evaluate_lqr
    base = evaluate_lqr(oracle=False, seed=0)
    oracle = evaluate_lqr(oracle=True, seed=0)
    print(base["pos_err_3d_mean"], oracle["pos_err_3d_mean"])
"""

from __future__ import annotations

import copy
import dataclasses
import functools
import inspect
import math
import os
import time
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Callable, Mapping, Sequence

import gymnasium as gym
import mujoco
import numpy as np
from gymnasium import spaces
from gymnasium.utils import seeding
from gymnasium.vector import AutoresetMode, VectorEnv
from gymnasium.vector.utils import batch_space

from controllers.references import Hover, Lemniscate, Transect, Waypoints, random_passes, stack
from sim.field import DownwashField
from sim.params import LEADER_POSITION, SEPARATION_RANGE
from sim.predictor import OraclePredictor, ZeroPredictor
from sim.scene import Scene, build_scene
from sim.simulator import STATUS_DIVERGED, STATUS_GROUND, STATUS_OK, STATUS_VEHICLE, SimConfig, Simulator

__all__ = [
    "ACTION_MODES",
    "REFERENCES",
    "PREDICTORS",
    "CONTROL_HZ_ALLOWED",
    "DEFAULT_MAX_EPISODE_STEPS",
    "DEFAULT_FIELD_RANDOMIZATION",
    "FIELD_RANDOMIZABLE",
    "OBSERVATION",
    "OBS_DIM",
    "REWARD_TERMS",
    "STATUS_LEFT_BOX",
    "STATUS_NAMES",
    "FollowerConfig",
    "make_config",
    "DownwashFollowerEnv",
    "DownwashFollowerVectorEnv",
    "evaluate_lqr",
    "env_steps_per_s_single",
    "env_steps_per_s_vector",
]

ACTION_MODES = ("residual", "acceleration")
REFERENCES = ("hover", "lemniscate", "transect", "passes")
PREDICTORS = ("none", "oracle")
DEFAULT_ACTION_BOUND = {"residual": 5.0, "acceleration": 10.0}  # m/s^2, per axis
MAX_ACTION_BOUND = 20.0  # m/s^2, largest accepted action_bound
# Hz, controller (= env step) rates offered; those dividing the autopilot grid (100 Hz
# with the default sim.params.RATES: all of them) are accepted.
CONTROL_HZ_ALLOWED = (10, 20, 25, 50, 100)
MIN_FOLLOWER_HEIGHT = 0.3  # m, the lowest reference height a leader position / separation may give
DEFAULT_MAX_EPISODE_STEPS = 500  # env steps (10 s at 50 Hz)
STATUS_LEFT_BOX = 4  # env-level status: the follower left the tracking box around its reference
STATUS_NAMES = MappingProxyType({
    STATUS_OK: "ok", STATUS_DIVERGED: "diverged", STATUS_GROUND: "ground_collision",
    STATUS_VEHICLE: "vehicle_collision", STATUS_LEFT_BOX: "left_box",
})
# DownwashField constants that domain randomisation may scale (the fade edges are left out:
# scaling them independently could invert the smoothstep).
FIELD_RANDOMIZABLE = (
    "strength", "strength_depth", "width0", "width_slope", "approach_gain", "approach_speed",
    "radial_gain", "radial_offset", "radial_speed_gain", "radial_speed", "leader_speed_scale",
)
DEFAULT_FIELD_RANDOMIZATION = MappingProxyType({"strength": (0.7, 1.3), "width0": (0.8, 1.2), "width_slope": (0.8, 1.2)})
MASS_SCALE_RANGE = (0.5, 1.5)  # -, allowed true-mass factors (thrust-to-weight 2.3 stays > 1.5)
FIELD_SCALE_RANGE = (0.1, 5.0)  # -, allowed field-constant factors
# Shape parameters each reference accepts in `reference_kwargs` (passed to controllers.references).
REFERENCE_KWARGS = MappingProxyType({
    "hover": ("offset",),
    "lemniscate": ("half_length", "half_width", "period"),
    "transect": ("x_offset", "half_length", "period"),
    "passes": ("speed_range", "max_offset", "pass_half_length", "duration", "hover_prob", "hover_radius",
               "hover_time_range", "reposition_speed", "min_move_time"),
})
_ERROR_CAP = 10.0  # m and m/s: position/velocity errors in the reward are capped (a diverged state is not finite)

LEADER, FOLLOWER = 0, 1  # vehicle indices in the scene ("alpha", "bravo")

# ----------------------------------------------------------------------------- observation

# (name, size, unit, frame, bound): the observation is their concatenation, float64, each
# entry clipped to [-bound, bound] (a bound never reached in a live episode: the tracking
# box terminates first; only a diverged world's last observation can be clipped).
OBSERVATION: tuple[tuple[str, int, str, str, float], ...] = (
    ("dp", 3, "m", "world", 10.0),  # p_follower - p_leader, Kalman estimates
    ("v_follower", 3, "m/s", "world", 20.0),  # follower velocity, Kalman estimate
    ("v_leader", 3, "m/s", "world", 20.0),  # leader velocity, Kalman estimate
    ("pos_error", 3, "m", "world", 10.0),  # p_follower (estimate) - p_ref
    ("vel_error", 3, "m/s", "world", 25.0),  # v_follower (estimate) - v_ref
    ("ref_acc", 3, "m/s^2", "world", 25.0),  # reference acceleration (feed-forward)
    ("follower_x_axis", 3, "-", "world", 1.0),  # follower body x axis, R_b[:, 0] (heading)
    ("follower_z_axis", 3, "-", "world", 1.0),  # follower body z axis, R_b[:, 2] (thrust direction)
    ("leader_z_axis", 3, "-", "world", 1.0),  # leader body z axis, R_a[:, 2] (the wake's axis)
    ("last_action", 3, "m/s^2", "world", math.nan),  # previous action as applied; bound = action bound
)
OBS_DIM = sum(size for _, size, *_ in OBSERVATION)
_OBS_SLICES = {}
_offset = 0
for _name, _size, *_ in OBSERVATION:
    _OBS_SLICES[_name] = slice(_offset, _offset + _size)
    _offset += _size
del _offset, _name, _size

# Reward terms, summed in this order: reward = sum(info["reward_" + name] for name in REWARD_TERMS).
REWARD_TERMS = ("alive", "position", "velocity", "action", "action_rate", "termination")


# ----------------------------------------------------------------------------- configuration


@dataclass(frozen=True)
class FollowerConfig:
    """Options of the follower envs (each is a `gymnasium.make` keyword).

    Task
        action_mode: "residual" (action added to the LQR acceleration command: the
            compensation task) or "acceleration" (the follower's whole acceleration
            command, gravity excluded; its LQR is bypassed, the yaw-rate command
            still comes from the LQR; the leader always flies its LQR).
        action_bound: m/s^2 per axis, the Box bound (default 5 residual, 10
            acceleration; allowed (0, 20]). Actions outside are clipped.
        reference: "hover" | "lemniscate" | "transect" | "passes" (the follower's path).
        reference_kwargs: shape parameters of the reference, passed to
            `controllers.references`: hover {offset (3,) m from the point below the
            leader}; lemniscate {half_length, half_width (m), period (s)}; transect
            {x_offset, half_length (m), period (s)}; passes {speed_range (m/s),
            max_offset, pass_half_length (m), duration (s, default 60; afterwards the
            last point is held), hover_prob, hover_radius, hover_time_range,
            reposition_speed, min_move_time}.
        separation: m, vertical distance of the reference below the leader: a float,
            or (low, high) drawn uniformly per episode (passes: per waypoint); both
            within 0.3-2.0 m.
        leader_position: (3,) m, world frame, where the leader hovers.
        random_phase: start lemniscate/transect episodes at a uniformly drawn point
            of the period (False: at t = 0, the tip / the far end).
        control_hz: controller (= env step) rate, Hz: one of 10, 20, 25, 50, 100 (it
            must divide the 100 Hz autopilot grid). Default 50 (10 physics steps).
        predictor: "none" or "oracle" (the LQR subtracts the true mean field,
            evaluated at 45 Hz; residual mode only).
    Downwash field
        c4_amplitude, swirl, skew: the field's misspecification knobs (see
            `sim.field.DownwashField`); all 0 by default.
        field: a custom field object with `DownwashField`'s call signature (knobs and
            field randomisation then need a `DownwashField`).
        field_randomization: None, "default" (strength x U(0.7, 1.3), width0 and
            width_slope x U(0.8, 1.2)) or {constant: (low, high)} factors drawn per
            episode, factors in 0.1-5, constants from FIELD_RANDOMIZABLE.
        mass_randomization: None or (low, high): the follower's true mass (and
            inertia) scaled by a factor drawn per episode, within 0.5-1.5. The
            controller keeps the nominal mass.
    Termination and reward
        max_tracking_error: m, the tracking box: an episode terminates when the
            follower's true position is farther than this from its reference
            (allowed (0, 5]); also on collision or divergence.
        alive_reward, position_cost_weight, velocity_cost_weight, action_cost_weight,
            action_rate_cost_weight, termination_penalty: reward weights, >= 0 (see
            `DownwashFollowerEnv`).
    Other
        sim_config: `sim.simulator.SimConfig` (noise, turbulence, LQR weights);
            its controller rate is replaced by control_hz.
        render_width, render_height: pixels of `render()`, at most 640 x 480.
    """

    action_mode: str = "residual"
    action_bound: float | None = None
    reference: str = "lemniscate"
    reference_kwargs: Mapping[str, Any] | None = None
    separation: float | tuple[float, float] = 0.6
    leader_position: tuple[float, float, float] = LEADER_POSITION
    random_phase: bool = True
    control_hz: int = 50
    predictor: str = "none"
    c4_amplitude: float = 0.0
    swirl: float = 0.0
    skew: float = 0.0
    field: Any = None
    field_randomization: str | Mapping[str, tuple[float, float]] | None = None
    mass_randomization: tuple[float, float] | None = None
    max_tracking_error: float = 1.0
    alive_reward: float = 1.0
    position_cost_weight: float = 2.0
    velocity_cost_weight: float = 0.5
    action_cost_weight: float = 0.05
    action_rate_cost_weight: float = 0.05
    termination_penalty: float = 50.0
    sim_config: SimConfig | None = None
    render_width: int = 480
    render_height: int = 360

    def __post_init__(self) -> None:
        _validate(self)

    # derived, validated values
    @property
    def bound(self) -> float:
        """m/s^2, the action Box bound per axis."""
        return DEFAULT_ACTION_BOUND[self.action_mode] if self.action_bound is None else float(self.action_bound)

    @property
    def separation_range(self) -> tuple[float, float]:
        return _separation_range(self.separation)

    @property
    def field_scales(self) -> dict[str, tuple[float, float]]:
        """{constant: (low, high)} factors, in a fixed (sorted) order; empty when off."""
        fr = self.field_randomization
        if fr is None:
            return {}
        if isinstance(fr, str):
            fr = DEFAULT_FIELD_RANDOMIZATION
        return {k: (float(fr[k][0]), float(fr[k][1])) for k in sorted(fr)}


def _options() -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(FollowerConfig))


def make_config(options: Mapping[str, Any] | None = None) -> FollowerConfig:
    """A validated `FollowerConfig` from keyword options; unknown names raise TypeError."""
    options = dict(options or {})
    allowed = _options()
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise TypeError(f"unknown option(s) {unknown}; allowed: {', '.join(allowed)}")
    return FollowerConfig(**options)


def _number(name: str, value: Any, unit: str, lo: float, hi: float, *, lo_open: bool = False) -> float:
    """A finite float in [lo, hi] (or (lo, hi]), else ValueError naming it and the range."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected a number ({unit}), got {value!r}") from None
    ok = (v > lo if lo_open else v >= lo) and v <= hi and math.isfinite(v)
    if not ok:
        rng = f"({lo}, {hi}]" if lo_open else f"[{lo}, {hi}]"
        raise ValueError(f"{name}: got {value!r}; allowed {rng} {unit}")
    return v


def _pair(name: str, value: Any, unit: str, lo: float, hi: float) -> tuple[float, float]:
    try:
        a, b = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ValueError(f"{name}: expected (low, high) within {lo}-{hi} {unit}, got {value!r}") from None
    if not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi):
        raise ValueError(f"{name}: got {value!r}; allowed (low, high) with {lo} <= low <= high <= {hi} {unit}")
    return a, b


def _separation_range(sep: Any) -> tuple[float, float]:
    lo, hi = SEPARATION_RANGE
    if np.ndim(sep) == 0:
        s = _number("separation", sep, "m", lo, hi)
        return s, s
    return _pair("separation", sep, "m", lo, hi)


def _control_hz_allowed(rates) -> tuple[int, ...]:
    autopilot_hz = 1.0 / rates.autopilot_dt
    return tuple(hz for hz in CONTROL_HZ_ALLOWED if abs(autopilot_hz / hz - round(autopilot_hz / hz)) < 1e-9)


def _validate(c: FollowerConfig) -> None:
    if c.action_mode not in ACTION_MODES:
        raise ValueError(f"action_mode: got {c.action_mode!r}; allowed: {', '.join(ACTION_MODES)}")
    if c.action_bound is not None:
        _number("action_bound", c.action_bound, "m/s^2", 0.0, MAX_ACTION_BOUND, lo_open=True)
    if c.reference not in REFERENCES:
        raise ValueError(f"reference: got {c.reference!r}; allowed: {', '.join(REFERENCES)}")
    if c.reference_kwargs is not None:
        if not isinstance(c.reference_kwargs, Mapping):
            raise ValueError(f"reference_kwargs: expected a dict, got {type(c.reference_kwargs).__name__}")
        unknown = sorted(set(c.reference_kwargs) - set(REFERENCE_KWARGS[c.reference]))
        if unknown:
            raise ValueError(
                f"reference_kwargs: unknown {unknown} for reference {c.reference!r}; "
                f"allowed: {', '.join(REFERENCE_KWARGS[c.reference])}"
            )
    sep_lo, sep_hi = _separation_range(c.separation)
    try:
        leader = np.array(c.leader_position, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"leader_position: expected (x, y, z) in m, got {c.leader_position!r}") from None
    if leader.shape != (3,) or not np.all(np.isfinite(leader)):
        raise ValueError(f"leader_position: expected 3 finite numbers (m), got {c.leader_position!r}")
    if not (leader[2] - sep_hi >= MIN_FOLLOWER_HEIGHT and leader[2] <= 20.0):
        raise ValueError(
            f"leader_position: z = {leader[2]} m with separation up to {sep_hi} m puts the reference below "
            f"{MIN_FOLLOWER_HEIGHT} m; allowed z in [{MIN_FOLLOWER_HEIGHT} + separation, 20] m"
        )
    if not isinstance(c.random_phase, (bool, np.bool_)):
        raise ValueError(f"random_phase: expected True or False, got {c.random_phase!r}")
    base = c.sim_config if c.sim_config is not None else SimConfig()
    if not isinstance(base, SimConfig):
        raise ValueError(f"sim_config: expected a sim.simulator.SimConfig, got {type(base).__name__}")
    allowed_hz = _control_hz_allowed(base.rates)
    if isinstance(c.control_hz, bool) or c.control_hz not in allowed_hz:
        raise ValueError(
            f"control_hz: got {c.control_hz!r}; allowed: {', '.join(map(str, allowed_hz))} Hz "
            f"(the controller runs on the {1.0 / base.rates.autopilot_dt:g} Hz autopilot grid)"
        )
    if c.predictor not in PREDICTORS:
        raise ValueError(f"predictor: got {c.predictor!r}; allowed: {', '.join(PREDICTORS)}")
    if c.predictor != "none" and c.action_mode != "residual":
        raise ValueError(
            f"predictor: {c.predictor!r} only acts on the LQR command, which action_mode='acceleration' "
            "replaces; use action_mode='residual' or predictor='none'"
        )
    _number("c4_amplitude", c.c4_amplitude, "-", -0.99, 0.99)
    _number("swirl", c.swirl, "-", -10.0, 10.0)
    _number("skew", c.skew, "s/m", 0.0, 10.0)
    knobs = any(float(getattr(c, k)) != 0.0 for k in ("c4_amplitude", "swirl", "skew"))
    fr = c.field_randomization
    if fr is not None:
        if isinstance(fr, str):
            if fr != "default":
                raise ValueError(f"field_randomization: got {fr!r}; allowed: None, 'default' or {{constant: (low, high)}}")
        elif isinstance(fr, Mapping):
            unknown = sorted(set(fr) - set(FIELD_RANDOMIZABLE))
            if unknown:
                raise ValueError(f"field_randomization: unknown constant(s) {unknown}; allowed: {', '.join(FIELD_RANDOMIZABLE)}")
            for k, v in fr.items():
                _pair(f"field_randomization[{k!r}]", v, "(factor)", *FIELD_SCALE_RANGE)
        else:
            raise ValueError(f"field_randomization: expected None, 'default' or a dict, got {type(fr).__name__}")
    if c.field is not None:
        if not callable(c.field):
            raise ValueError(f"field: expected a callable field(p_a, v_a, R_a, p_b, v_b), got {type(c.field).__name__}")
        if (knobs or fr is not None) and not isinstance(c.field, DownwashField):
            raise ValueError(
                "field: c4_amplitude/swirl/skew and field_randomization need a sim.field.DownwashField, "
                f"got {type(c.field).__name__}"
            )
    if c.mass_randomization is not None:
        _pair("mass_randomization", c.mass_randomization, "(factor)", *MASS_SCALE_RANGE)
    _number("max_tracking_error", c.max_tracking_error, "m", 0.0, 5.0, lo_open=True)
    for name in ("alive_reward", "position_cost_weight", "velocity_cost_weight", "action_cost_weight",
                 "action_rate_cost_weight", "termination_penalty"):
        _number(name, getattr(c, name), "(reward weight)", 0.0, 1e6)
    for name, hi in (("render_width", 640), ("render_height", 480)):
        v = getattr(c, name)
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 16 <= v <= hi:
            raise ValueError(f"{name}: got {v!r}; allowed integers 16-{hi} (pixels)")
    # Reference shape parameters: let the reference classes check them (they name the argument).
    _reference_probe(c)


# Limits on the reference's shape, so that the observation bounds are never reached.
REFERENCE_LIMITS = {"extent": 5.0, "speed": 5.0, "acc": 10.0}  # m from the point below the leader, m/s, m/s^2


def _reference_probe(c: FollowerConfig) -> None:
    """Build the reference once (its class checks its arguments, naming them) and check its
    extent, speed and acceleration against REFERENCE_LIMITS."""
    kw = dict(c.reference_kwargs or {})
    center = np.array(c.leader_position, float) - [0.0, 0.0, c.separation_range[0]]
    lim = REFERENCE_LIMITS
    if c.reference == "passes":
        random_passes(np.random.default_rng(0), 1, c.leader_position, depth_range=c.separation_range,
                      n_segments=1, **{k: v for k, v in kw.items() if k != "duration"})
        if "duration" in kw:
            _number("reference_kwargs['duration']", kw["duration"], "s", 0.0, 1e5, lo_open=True)
        defaults = inspect.signature(random_passes).parameters
        get = lambda k: float(kw.get(k, defaults[k].default))  # noqa: E731
        extent = max(get("max_offset") + get("pass_half_length"), get("hover_radius"))
        if extent > lim["extent"]:
            raise ValueError(
                f"reference_kwargs: passes reach {extent:g} m from the wake axis "
                f"(max_offset + pass_half_length, hover_radius); allowed up to {lim['extent']} m"
            )
        return  # speeds are limited to 1 m/s by random_passes
    n = 257  # sample times over one period, as worlds of one batched reference
    if c.reference == "hover":
        off = np.array(kw.get("offset", (0.0, 0.0, 0.0)), dtype=float)
        if off.shape != (3,) or not np.all(np.isfinite(off)):
            raise ValueError(f"reference_kwargs['offset']: expected 3 finite numbers (m), got {kw.get('offset')!r}")
        ref = Hover(center + off, n_worlds=n)
    elif c.reference == "lemniscate":
        ref = Lemniscate(center, n_worlds=n, **kw)
    else:
        ref = Transect(center, n_worlds=n, **kw)
    sample = ref(np.linspace(0.0, float(np.max(getattr(ref, "period", 1.0))), n))
    extent = float(np.max(np.linalg.norm(sample.pos - center, axis=-1)))
    speed = float(np.max(np.linalg.norm(sample.vel, axis=-1)))
    acc = float(np.max(np.linalg.norm(sample.acc, axis=-1)))
    if extent > lim["extent"] or speed > lim["speed"] or acc > lim["acc"]:
        raise ValueError(
            f"reference_kwargs {kw}: the {c.reference} reaches {extent:.3g} m from the point below the "
            f"leader, {speed:.3g} m/s, {acc:.3g} m/s^2; allowed up to {lim['extent']} m, "
            f"{lim['speed']} m/s, {lim['acc']} m/s^2"
        )


# ----------------------------------------------------------------------------- episodes


@dataclass(frozen=True)
class _Episode:
    """What is drawn per episode from the env's generator (the same draws in every env class)."""

    sim_seed: int  # seeds the world's noise (motion capture, turbulence)
    separation: float  # m
    phase: float  # -, fraction of the period at which the reference starts
    field_scales: tuple[float, ...]  # factors, in FollowerConfig.field_scales order
    mass_scale: float  # -, true / nominal follower mass
    pattern: tuple[np.ndarray, np.ndarray, np.ndarray] | None  # passes: points, durations, dwell


def _draw_episode(rng: np.random.Generator, cfg: FollowerConfig) -> _Episode:
    """Draw one episode's parameters, always in the same order (seed, separation, phase, ...)."""
    sim_seed = int(rng.integers(0, 2**63 - 1))
    lo, hi = cfg.separation_range
    separation = float(rng.uniform(lo, hi))
    phase = float(rng.uniform(0.0, 1.0))
    scales = tuple(float(rng.uniform(a, b)) for a, b in cfg.field_scales.values())
    mass_scale = float(rng.uniform(*cfg.mass_randomization)) if cfg.mass_randomization is not None else 1.0
    pattern = None
    if cfg.reference == "passes":
        kw = dict(cfg.reference_kwargs or {})
        wp = random_passes(rng, 1, cfg.leader_position, depth_range=cfg.separation_range, **kw)
        k = int(wp.n_points[0])
        pattern = (wp.points[0, :k].copy(), wp.durations[0, : k - 1].copy(), wp.dwell[0, :k].copy())
        separation = float(cfg.leader_position[2] - pattern[0][0, 2])  # the first waypoint's depth
    return _Episode(sim_seed, separation, phase, scales, mass_scale, pattern)


def _nominal_episode(cfg: FollowerConfig) -> _Episode:
    """A placeholder episode for construction (before the first reset draws one)."""
    pattern = None
    if cfg.reference == "passes":
        below = np.array(cfg.leader_position, float) - [0.0, 0.0, cfg.separation_range[0]]
        pattern = (below[None], np.zeros(0), np.zeros(1))
    n = len(cfg.field_scales)
    return _Episode(0, cfg.separation_range[0], 0.0, (1.0,) * n, 1.0, pattern)


def _reset_info(cfg: FollowerConfig, ep: _Episode) -> dict[str, Any]:
    """The info of reset(): the episode's drawn parameters (plain Python numbers)."""
    info: dict[str, Any] = {"separation": ep.separation, "mass_scale": ep.mass_scale}
    for name, s in zip(cfg.field_scales, ep.field_scales):
        info[f"field_scale_{name}"] = s
    return info


class _Cached:
    """A reference that returns its last sample again when asked for the same times.

    The env samples the reference at the end of a step (observation, reward) and the
    next controller tick samples it at the same times: one evaluation serves both.
    Samples are shared between callers, which only read them.
    """

    def __init__(self, ref: Any):
        self.ref = ref
        self.n_worlds = ref.n_worlds
        self.duration = ref.duration
        self._t: np.ndarray | None = None
        self._sample = None

    def __call__(self, t: Any):
        t = np.asarray(t, dtype=float)
        if self._t is None or t.shape != self._t.shape or not np.array_equal(t, self._t):
            self._sample = self.ref(t)
            self._t = t.copy()  # the simulator updates its clock in place at reset
        return self._sample


class _TimeShifted:
    """A batched reference sampled at t + t0 (per-world start phase)."""

    def __init__(self, ref: Any, t0: np.ndarray):
        self.ref, self.t0 = ref, t0
        self.n_worlds = ref.n_worlds
        self.duration = ref.duration

    def __call__(self, t: Any):
        return self.ref(np.asarray(t, dtype=float) + self.t0)


@functools.lru_cache(maxsize=1)
def _scene() -> Scene:
    """The two-vehicle scene, compiled once per process (read-only: physics copies on write)."""
    return build_scene()


# ----------------------------------------------------------------------------- the batched engine


class _FollowerWorlds:
    """W worlds of the follower task on one Simulator: per-world episodes, batched obs and reward.

    Everything per step is batched over worlds; per-world Python runs only at reset.
    """

    def __init__(self, cfg: FollowerConfig, n_worlds: int, n_threads: int = 0):
        self.cfg = cfg
        self.W = W = int(n_worlds)
        self.scene = _scene()
        base = cfg.sim_config if cfg.sim_config is not None else SimConfig()
        per_control = int(round(1.0 / (base.rates.autopilot_dt * cfg.control_hz)))
        self.sim_config = dataclasses.replace(base, rates=dataclasses.replace(base.rates, autopilot_per_control=per_control))
        self.leader = np.array(cfg.leader_position, dtype=float)
        self.bound = cfg.bound
        self.residual_mode = cfg.action_mode == "residual"

        # field: the knobs once; per-world constants when randomised
        field = cfg.field if cfg.field is not None else DownwashField()
        knobs = {k: float(getattr(cfg, k)) for k in ("c4_amplitude", "swirl", "skew") if float(getattr(cfg, k)) != 0.0}
        self.base_field = dataclasses.replace(field, **knobs) if knobs else field
        self.scale_names = tuple(cfg.field_scales)
        self.episodes: list[_Episode] = [_nominal_episode(cfg)] * W

        # follower reference: the class's shape parameters, per-world centers and phases
        self.ref_kwargs = dict(cfg.reference_kwargs or {})
        self.follower_body = np.array([self.scene.body_ids[FOLLOWER]])
        self.nominal_mass = float(self.scene.model.body_mass[self.scene.body_ids[FOLLOWER]])  # kg

        field_now = self._field()
        self.sim = Simulator(
            self.scene, self._reference(), [0] * W, config=self.sim_config, field=field_now,
            predictor=self._predictor(field_now), n_threads=n_threads,
        )
        V = self.sim.V
        self.last_action = np.zeros((W, 3))
        self._command = np.zeros((W, V, 3)) if self.residual_mode else np.full((W, V, 3), np.nan)
        self._obs_cache: tuple[np.ndarray, Any] | None = None  # attitudes and reference of the last step
        low, high = _obs_bounds(self.bound)
        self.obs_low, self.obs_high = low, high

    # ---------------------------------------------------------------- per-world parameters
    def _field(self) -> Any:
        if not self.scale_names:
            return self.base_field
        scales = np.array([ep.field_scales for ep in self.episodes])  # (W, n)
        values = {
            name: (float(getattr(self.base_field, name)) * scales[:, i]).reshape(self.W, 1, 1)
            for i, name in enumerate(self.scale_names)
        }
        return dataclasses.replace(self.base_field, **values)

    def _predictor(self, field: Any) -> Any:
        return OraclePredictor(field) if self.cfg.predictor == "oracle" else ZeroPredictor()

    def _reference(self):
        cfg, W, eps = self.cfg, self.W, self.episodes
        sep = np.array([ep.separation for ep in eps])
        below = self.leader - sep[:, None] * np.array([0.0, 0.0, 1.0])  # (W, 3) m
        kw = self.ref_kwargs
        if cfg.reference == "hover":
            follower = Hover(below + np.array(kw.get("offset", (0.0, 0.0, 0.0)), dtype=float), n_worlds=W)
        elif cfg.reference == "lemniscate":
            follower = Lemniscate(below, n_worlds=W, **kw)
        elif cfg.reference == "transect":
            follower = Transect(below, n_worlds=W, **kw)
        else:
            follower = Waypoints.from_patterns(
                [ep.pattern[0] for ep in eps], [ep.pattern[1] for ep in eps], [ep.pattern[2] for ep in eps]
            )
        t0 = np.zeros(W)
        if cfg.random_phase and cfg.reference in ("lemniscate", "transect"):
            t0 = np.array([ep.phase for ep in eps]) * follower.period
        return _Cached(stack([Hover(self.leader, n_worlds=W), _TimeShifted(follower, t0)]))

    # ---------------------------------------------------------------- reset
    def reset_worlds(self, worlds: Sequence[int], episodes: Sequence[_Episode]) -> None:
        """Start the given worlds on the given episodes (their reference's t = 0 state)."""
        worlds = np.asarray(worlds, dtype=np.int64)
        for w, ep in zip(worlds, episodes):
            self.episodes[w] = ep
        sim = self.sim
        if self.scale_names:
            sim.field = self._field()
            sim.predictor = self._predictor(sim.field)
        if self.cfg.mass_randomization is not None:
            self._set_follower_mass(worlds, np.array([ep.mass_scale for ep in episodes]))
        sim.reset(worlds, seeds=[ep.sim_seed for ep in episodes], reference=self._reference())
        self.last_action[worlds] = 0.0
        self._obs_cache = None

    def _set_follower_mass(self, worlds: np.ndarray, scale: np.ndarray) -> None:
        """True follower mass = nominal x scale (inertia likewise); the controller keeps nominal."""
        ph = self.sim.physics
        ids = self.follower_body
        ph.set_body_mass(worlds, ids, (self.nominal_mass * scale)[:, None])

    # ---------------------------------------------------------------- step
    def check_actions(self, action: Any, shape: tuple[int, ...]) -> np.ndarray:
        """Validate (shape, finite) and clip to the bound; ValueError before any stepping."""
        try:
            a = np.array(action, dtype=np.float64)
        except (TypeError, ValueError):
            raise ValueError(f"action: expected a float array of shape {shape} (m/s^2), got {action!r}") from None
        if a.shape != shape:
            raise ValueError(f"action: expected shape {shape} (m/s^2, world frame), got {a.shape}")
        if not np.all(np.isfinite(a)):
            raise ValueError(f"action: must be finite (m/s^2), got {a.tolist()}")
        return np.clip(a, -self.bound, self.bound, out=a)

    def step(self, actions: np.ndarray, stepping: np.ndarray | None = None):
        """Advance the `stepping` worlds (default all) one controller period with (W, 3) actions.

        Worlds not stepping must be reset before their next step. Returns
        (terms {name: (W,)}, terminated (W,), status (W,), pos_err (W,), vel_err (W,)).
        """
        sim = self.sim
        if stepping is not None and not stepping.all():
            sim.active &= stepping
        cmd = self._command
        cmd[:, FOLLOWER] = actions
        if sim.active.any():
            if self.residual_mode:
                sim.tick(residual=cmd)
            else:
                sim.tick(override=cmd)
        true = sim.true_states()
        ref = sim.reference(sim.t)
        pos_err = _capped_norm(true.pos[:, FOLLOWER] - ref.pos[:, FOLLOWER])
        vel_err = _capped_norm(true.vel[:, FOLLOWER] - ref.vel[:, FOLLOWER])
        left = ~(pos_err <= self.cfg.max_tracking_error)
        status = np.where(sim.status != STATUS_OK, sim.status, np.where(left, STATUS_LEFT_BOX, STATUS_OK))
        terminated = status != STATUS_OK

        c, b2 = self.cfg, self.bound * self.bound
        da = actions - self.last_action
        terms = {
            "alive": c.alive_reward * (~terminated),
            "position": -c.position_cost_weight * pos_err,
            "velocity": -c.velocity_cost_weight * vel_err,
            "action": -c.action_cost_weight * (_sumsq(actions) / b2),
            "action_rate": -c.action_rate_cost_weight * (_sumsq(da) / b2),
            "termination": -c.termination_penalty * terminated,
        }
        if stepping is None:
            self.last_action[:] = actions
        else:
            self.last_action[stepping] = actions[stepping]
        self._obs_cache = (true.rot, ref)
        return terms, terminated, status, pos_err, vel_err

    # ---------------------------------------------------------------- observation
    def observe(self, fresh: bool = True) -> np.ndarray:
        """(W, OBS_DIM) float64, the layout of OBSERVATION, clipped to its bounds.

        fresh=False reuses the attitudes and reference of the last step (no reset since).
        """
        sim = self.sim
        if fresh or self._obs_cache is None:
            rot = sim.true_states().rot
            ref = sim.reference(sim.t)
        else:
            rot, ref = self._obs_cache
        pe, ve = sim.pos_est, sim.vel_est
        o = np.empty((self.W, OBS_DIM))
        s = _OBS_SLICES
        o[:, s["dp"]] = pe[:, FOLLOWER] - pe[:, LEADER]
        o[:, s["v_follower"]] = ve[:, FOLLOWER]
        o[:, s["v_leader"]] = ve[:, LEADER]
        o[:, s["pos_error"]] = pe[:, FOLLOWER] - ref.pos[:, FOLLOWER]
        o[:, s["vel_error"]] = ve[:, FOLLOWER] - ref.vel[:, FOLLOWER]
        o[:, s["ref_acc"]] = ref.acc[:, FOLLOWER]
        o[:, s["follower_x_axis"]] = rot[:, FOLLOWER, :, 0]
        o[:, s["follower_z_axis"]] = rot[:, FOLLOWER, :, 2]
        o[:, s["leader_z_axis"]] = rot[:, LEADER, :, 2]
        o[:, s["last_action"]] = self.last_action
        np.clip(o, self.obs_low, self.obs_high, out=o)
        nan = np.isnan(o)
        if nan.any():  # only a diverged world's state
            o[nan] = 0.0
        return o


# np.vecdot (NumPy >= 2): one generalised-ufunc call per (W, 3) array, each row's sum in
# the same order whatever W (so batched and single worlds agree bit for bit).
_dot: Callable[[np.ndarray, np.ndarray], np.ndarray] = getattr(
    np, "vecdot", lambda a, b: np.einsum("...i,...i->...", a, b)
)


def _sumsq(x: np.ndarray) -> np.ndarray:
    """(W, 3) -> (W,) sum of squares."""
    return _dot(x, x)


def _capped_norm(x: np.ndarray) -> np.ndarray:
    """(W, 3) -> (W,) Euclidean norm, non-finite or above _ERROR_CAP replaced by the cap."""
    n = np.sqrt(_sumsq(x))
    return np.where(n <= _ERROR_CAP, n, _ERROR_CAP)


def _obs_bounds(action_bound: float) -> tuple[np.ndarray, np.ndarray]:
    high = np.concatenate([np.full(size, action_bound if name == "last_action" else bound)
                           for name, size, _, _, bound in OBSERVATION])
    return -high, high


def _spaces(cfg: FollowerConfig) -> tuple[spaces.Box, spaces.Box]:
    low, high = _obs_bounds(cfg.bound)
    obs = spaces.Box(low, high, dtype=np.float64)
    act = spaces.Box(-cfg.bound, cfg.bound, shape=(3,), dtype=np.float32)
    return obs, act


# ----------------------------------------------------------------------------- rendering

_HULL_RGBA = {LEADER: (0.95, 0.55, 0.05, 1.0), FOLLOWER: (0.05, 0.8, 0.9, 1.0)}  # orange leader, cyan follower
_REF_RGBA = (0.2, 0.9, 0.2, 0.5)  # translucent green sphere at the follower's reference


class _Renderer:
    """Offscreen frames with a free camera that keeps both vehicles in view.

    The camera looks at the midpoint of the two vehicles from a distance that grows
    with their separation; hulls and arms are tinted (leader orange, follower cyan)
    and a green sphere marks the follower's reference.
    """

    def __init__(self, scene: Scene, width: int, height: int):
        model = copy.copy(scene.model)  # tinted copy; the physics model is untouched
        for v, rgba in _HULL_RGBA.items():
            name = scene.vehicles[v]
            for g in ("hull", "arm0", "arm1", "arm2", "arm3"):
                model.geom_rgba[model.geom(f"{name}/{g}").id] = rgba
        self.model = model
        try:
            self._renderer = mujoco.Renderer(model, height=height, width=width)
        except (mujoco.FatalError, ImportError, AttributeError, OSError, RuntimeError) as e:
            raise RuntimeError(
                "render_mode='rgb_array' needs an OpenGL backend for offscreen rendering, and none could be "
                f"created (MUJOCO_GL={os.environ.get('MUJOCO_GL', '<unset>')!r}: {type(e).__name__}: {e}). "
                "Set MUJOCO_GL=egl (GPU, or Mesa's software EGL: apt-get install libegl1 libegl-mesa0 "
                "libgl1-mesa-dri libopengl0) or MUJOCO_GL=osmesa (apt-get install libosmesa6) in the "
                "environment before mujoco is imported."
            ) from e
        self.camera = mujoco.MjvCamera()
        self.camera.type = mujoco.mjtCamera.mjCAMERA_FREE
        self.camera.azimuth = 135.0  # deg
        self.camera.elevation = -20.0  # deg

    def render(self, data: mujoco.MjData, p_leader: np.ndarray, p_follower: np.ndarray, p_ref: np.ndarray) -> np.ndarray:
        """(height, width, 3) uint8."""
        mid = 0.5 * (p_leader + p_follower)
        dist = float(np.linalg.norm(p_follower - p_leader))
        cam = self.camera
        cam.lookat[:] = mid if np.all(np.isfinite(mid)) else 0.0
        cam.distance = 0.6 + 1.3 * (dist if math.isfinite(dist) else 1.0)  # m: both in a 45 deg view
        r = self._renderer
        r.update_scene(data, camera=cam)
        scn = r.scene
        if scn.ngeom < scn.maxgeom and np.all(np.isfinite(p_ref)):
            mujoco.mjv_initGeom(
                scn.geoms[scn.ngeom], mujoco.mjtGeom.mjGEOM_SPHERE, np.array([0.03, 0.0, 0.0]),
                np.asarray(p_ref, float), np.eye(3).ravel(), np.array(_REF_RGBA, np.float32),
            )
            scn.ngeom += 1
        return r.render()

    def close(self) -> None:
        self._renderer.close()


def _render_world(worlds: _FollowerWorlds, renderer: _Renderer, w: int) -> np.ndarray:
    sim = worlds.sim
    pos = sim.true_states().pos[w]  # (V, 3) m
    ref = sim.reference(sim.t).pos[w, FOLLOWER]
    return renderer.render(sim.physics.mjdata(w), pos[LEADER], pos[FOLLOWER], ref)


# ----------------------------------------------------------------------------- the single env


class DownwashFollowerEnv(gym.Env):
    """The follower tracks a reference below a hovering leader, in the leader's downwash.

    ## Actions
    Box(-b, b, (3,), float32), m/s^2, world frame (z up), b = `action_bound`
    (default 5 in residual mode, 10 in acceleration mode); clipped to the box; NaN,
    inf or a wrong shape raise ValueError before any stepping.

    - ``residual``: added to the follower's LQR acceleration command
      `u = a_ref - K (x - x_ref) - f_hat`; action 0 is the plain LQR (the
      compensation task: the ideal action cancels the downwash, -f).
    - ``acceleration``: the follower's whole acceleration command (gravity
      excluded; its feedback linearisation still turns it into thrust and tilt,
      tilt limited to 35 deg, vertical specific force >= 0.25 g).

    ## Observation
    Box, float64, (30,); the vehicle's own knowledge: positions and velocities are
    the Kalman-filtered motion-capture estimates at the observation time, attitudes
    the onboard (true) ones; the reference is sampled at the same time.

    | index | name            | meaning                                              | unit  | frame | bound |
    |-------|-----------------|------------------------------------------------------|-------|-------|-------|
    | 0-2   | dp              | p_follower - p_leader                                | m     | world | 10    |
    | 3-5   | v_follower      | follower velocity                                    | m/s   | world | 20    |
    | 6-8   | v_leader        | leader velocity                                      | m/s   | world | 20    |
    | 9-11  | pos_error       | p_follower - p_ref                                   | m     | world | 10    |
    | 12-14 | vel_error       | v_follower - v_ref                                   | m/s   | world | 25    |
    | 15-17 | ref_acc         | reference acceleration a_ref                         | m/s^2 | world | 25    |
    | 18-20 | follower_x_axis | follower body x axis R_b[:, 0] (heading)             | -     | world | 1     |
    | 21-23 | follower_z_axis | follower body z axis R_b[:, 2] (thrust direction)    | -     | world | 1     |
    | 24-26 | leader_z_axis   | leader body z axis R_a[:, 2] (the wake's axis)       | -     | world | 1     |
    | 27-29 | last_action     | previous action as applied (0 after reset)           | m/s^2 | world | b     |

    Entries are clipped to their bound (never reached in a live episode: the
    tracking box ends it first).

    ## Reward
    reward = sum of six terms, each in ``info["reward_<name>"]`` (REWARD_TERMS order),
    from the true state at the end of the step, e_p = p - p_ref, e_v = v - v_ref:

    | term        | value                                                   | default weight |
    |-------------|---------------------------------------------------------|----------------|
    | alive       | +alive_reward while the episode goes on                 | 1.0            |
    | position    | -position_cost_weight * norm(e_p)  (m)                  | 2.0            |
    | velocity    | -velocity_cost_weight * norm(e_v)  (m/s)                | 0.5            |
    | action      | -action_cost_weight * norm(a)^2 / b^2                   | 0.05           |
    | action_rate | -action_rate_cost_weight * norm(a - a_prev)^2 / b^2     | 0.05           |
    | termination | -termination_penalty on the terminating step            | 50.0           |

    The alive bonus and the termination penalty keep crashing from paying off;
    the action-rate term discourages chattering that the motors (30 ms lag) cannot
    follow. norm(e_p) and norm(e_v) are capped at 10 (a diverged state is not finite).

    ## Episode end
    terminated: collision with the ground or the leader, divergence (NaN, MuJoCo
    instability), or the follower farther than `max_tracking_error` (default 1 m)
    from its reference (the tracking box). ``info["status"]``: 0 ok, 1 diverged,
    2 ground collision, 3 vehicle collision, 4 left the box (STATUS_NAMES).
    truncated: by gymnasium's TimeLimit at the registered max_episode_steps.

    ## Info
    reset: the drawn episode parameters: ``separation`` (m; passes: the first
    waypoint's depth), ``mass_scale``, and ``field_scale_<constant>`` per randomised
    field constant. step: the reward terms ``reward_<name>``, ``position_error`` (m)
    and ``velocity_error`` (m/s) (true state, capped), ``status``.

    ## Options
    See `FollowerConfig` (every field is a keyword); unknown names raise TypeError
    naming the allowed ones, bad values ValueError naming the allowed range.
    `reset(options=...)` takes no options. Randomness: every episode draws its
    parameters and its noise seed from `self.np_random`.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50}

    def __init__(self, render_mode: str | None = None, **options: Any):
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed: None, {', '.join(self.metadata['render_modes'])}")
        self.config = cfg = make_config(options)
        self.render_mode = render_mode
        self.metadata = {**type(self).metadata, "render_fps": cfg.control_hz}
        self.observation_space, self.action_space = _spaces(cfg)
        self._worlds = _FollowerWorlds(cfg, 1)
        self._renderer: _Renderer | None = None

    @property
    def dt(self) -> float:
        """s, one env step (the controller period)."""
        return self._worlds.sim_config.rates.control_dt

    @property
    def simulator(self) -> Simulator:
        """The underlying `sim.simulator.Simulator` (one world), for diagnostics."""
        return self._worlds.sim

    def reset(self, *, seed: int | None = None, options: dict[str, Any] | None = None):
        super().reset(seed=seed)
        _check_reset_options(options, allowed=())
        ep = _draw_episode(self.np_random, self.config)
        self._worlds.reset_worlds([0], [ep])
        return self._worlds.observe()[0], _reset_info(self.config, ep)

    def step(self, action: Any):
        a = self._worlds.check_actions(action, (3,))
        terms, terminated, status, pos_err, vel_err = self._worlds.step(a[None], None)
        obs = self._worlds.observe(fresh=False)[0]
        info: dict[str, Any] = {f"reward_{k}": float(v[0]) for k, v in terms.items()}
        reward = 0.0
        for k in REWARD_TERMS:
            reward = reward + info[f"reward_{k}"]
        info["position_error"] = float(pos_err[0])
        info["velocity_error"] = float(vel_err[0])
        info["status"] = int(status[0])
        return obs, float(reward), bool(terminated[0]), False, info

    def render(self):
        if self.render_mode is None:
            gym.logger.warn(
                "render() called without a render_mode; make the env with render_mode='rgb_array'"
            )
            return None
        if self._renderer is None:
            self._renderer = _Renderer(self._worlds.scene, self.config.render_width, self.config.render_height)
        return _render_world(self._worlds, self._renderer, 0)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _check_reset_options(options: Mapping[str, Any] | None, allowed: tuple[str, ...]) -> None:
    if options:
        unknown = sorted(set(options) - set(allowed))
        if unknown:
            what = ", ".join(allowed) if allowed else "none (configure episodes through the env's options)"
            raise ValueError(f"reset options: unknown {unknown}; allowed: {what}")


# ----------------------------------------------------------------------------- the vector env


class DownwashFollowerVectorEnv(VectorEnv):
    """`num_envs` follower worlds on one `mujoco.batch.Batch`: Gymnasium's VectorEnv API.

    Observations (num_envs, 30), actions (num_envs, 3), rewards/terminations/
    truncations (num_envs,), infos a dict of arrays with ``_key`` masks, as
    `SyncVectorEnv` builds them. Autoreset: next step (`metadata["autoreset_mode"]`):
    the step after a world terminates or truncates resets it (its action is
    ignored, reward 0, the reset's observation and info). Step for step identical
    to `SyncVectorEnv` of `DownwashFollowerEnv`s with the same options and seeds:
    world i of `reset(seed=s)` uses seed s + i; `reset(seed=[...])` one per world.

    num_envs: worlds. max_episode_steps: truncation horizon (None or -1: none;
    `make_vec` passes the registered one). n_threads: Batch threads (0: all cores).
    Other keywords: `FollowerConfig` (see `DownwashFollowerEnv` for the spaces,
    reward and termination). `reset(options={"reset_mask": mask})` resets only
    the masked worlds. `render()` returns one frame per world.
    """

    metadata = {"render_modes": ["rgb_array"], "render_fps": 50, "autoreset_mode": AutoresetMode.NEXT_STEP}

    def __init__(
        self,
        num_envs: int = 8,
        render_mode: str | None = None,
        max_episode_steps: int | None = DEFAULT_MAX_EPISODE_STEPS,
        n_threads: int = 0,
        **options: Any,
    ):
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise ValueError(f"num_envs: expected an integer >= 1, got {num_envs!r}")
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode: got {render_mode!r}; allowed: None, {', '.join(self.metadata['render_modes'])}")
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer))
            or (max_episode_steps < 1 and max_episode_steps != -1)
        ):
            raise ValueError(f"max_episode_steps: expected None, -1 (no limit) or an integer >= 1, got {max_episode_steps!r}")
        self.config = cfg = make_config(options)
        self.num_envs = N = int(num_envs)
        self.render_mode = render_mode
        self.max_episode_steps = None if max_episode_steps in (None, -1) else int(max_episode_steps)
        self.metadata = {**type(self).metadata, "render_fps": cfg.control_hz}
        self.single_observation_space, self.single_action_space = _spaces(cfg)
        self.observation_space = batch_space(self.single_observation_space, N)
        self.action_space = batch_space(self.single_action_space, N)
        self._worlds = _FollowerWorlds(cfg, N, n_threads)
        self._rngs: list[np.random.Generator | None] = [None] * N
        self._autoreset = np.zeros(N, bool)
        self._elapsed = np.zeros(N, np.int64)
        self._renderer: _Renderer | None = None

    @property
    def dt(self) -> float:
        """s, one env step (the controller period)."""
        return self._worlds.sim_config.rates.control_dt

    @property
    def simulator(self) -> Simulator:
        """The underlying batched `sim.simulator.Simulator`, for diagnostics."""
        return self._worlds.sim

    def _rng(self, w: int) -> np.random.Generator:
        if self._rngs[w] is None:
            self._rngs[w], _ = seeding.np_random()
        return self._rngs[w]

    def _reset_worlds(self, worlds: np.ndarray) -> dict[str, np.ndarray]:
        """Draw episodes for `worlds` from their generators, reset them; returns their infos (W,)."""
        episodes = [_draw_episode(self._rng(int(w)), self.config) for w in worlds]
        self._worlds.reset_worlds(worlds, episodes)
        self._elapsed[worlds] = 0
        infos = [_reset_info(self.config, ep) for ep in episodes]
        out = {}
        for key in infos[0] if infos else ():
            arr = np.zeros(self.num_envs, dtype=type(infos[0][key]))
            arr[worlds] = [i[key] for i in infos]
            out[key] = arr
        return out

    def reset(self, *, seed: int | Sequence[int | None] | None = None, options: dict[str, Any] | None = None):
        N = self.num_envs
        if seed is None:
            seeds: list[int | None] = [None] * N
        elif isinstance(seed, (int, np.integer)):
            super().reset(seed=int(seed))
            seeds = [int(seed) + i for i in range(N)]
        else:
            seeds = list(seed)
            if len(seeds) != N:
                raise ValueError(f"seed: a list of seeds needs one per world ({N}), got {len(seeds)}")
        options = dict(options or {})
        mask = options.pop("reset_mask", None)
        _check_reset_options(options, allowed=("reset_mask",))
        if mask is None:
            mask = np.ones(N, bool)
        else:
            mask = np.asarray(mask)
            if mask.shape != (N,) or mask.dtype != np.bool_ or not mask.any():
                raise ValueError(f"reset options['reset_mask']: expected a bool array ({N},) with a True, got {mask!r}")
        worlds = np.flatnonzero(mask)
        for w in worlds:
            if seeds[w] is not None:
                self._rngs[w], _ = seeding.np_random(int(seeds[w]))
        reset_info = self._reset_worlds(worlds)
        self._autoreset[worlds] = False
        obs = self._worlds.observe()
        infos = _vector_infos(N, {}, np.zeros(N, bool), reset_info, mask)
        return obs, infos

    def step(self, actions: Any):
        N = self.num_envs
        a = self._worlds.check_actions(actions, (N, 3))
        resetting = self._autoreset
        stepping = ~resetting
        any_reset = bool(resetting.any())
        terms, terminated, status, pos_err, vel_err = self._worlds.step(a, stepping if any_reset else None)
        reward = np.zeros(N)
        for k in REWARD_TERMS:
            reward = reward + terms[k]
        self._elapsed += stepping
        truncated = self._elapsed >= self.max_episode_steps if self.max_episode_steps is not None else np.zeros(N, bool)
        step_info = {f"reward_{k}": terms[k] for k in REWARD_TERMS}
        step_info.update(position_error=pos_err, velocity_error=vel_err, status=status.astype(np.int64))
        reset_info: dict[str, np.ndarray] = {}
        if any_reset:
            worlds = np.flatnonzero(resetting)
            reset_info = self._reset_worlds(worlds)
            reward[resetting] = 0.0
            terminated = terminated & stepping
            truncated = truncated & stepping
            obs = self._worlds.observe()
        else:
            obs = self._worlds.observe(fresh=False)
        infos = _vector_infos(N, step_info, stepping, reset_info, resetting)
        self._autoreset = terminated | truncated
        return obs, reward, terminated, truncated, infos

    def render(self):
        if self.render_mode is None:
            gym.logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array'")
            return None
        if self._renderer is None:
            self._renderer = _Renderer(self._worlds.scene, self.config.render_width, self.config.render_height)
        return tuple(_render_world(self._worlds, self._renderer, w) for w in range(self.num_envs))

    def close_extras(self, **kwargs: Any) -> None:
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None


def _vector_infos(
    n: int, step_info: dict[str, np.ndarray], step_mask: np.ndarray,
    reset_info: dict[str, np.ndarray], reset_mask: np.ndarray,
) -> dict[str, np.ndarray]:
    """Infos as SyncVectorEnv assembles them: per key the values (0 where absent) and a `_key` mask."""
    out: dict[str, np.ndarray] = {}
    for info, mask in ((step_info, step_mask), (reset_info, reset_mask)):
        if not mask.any():
            continue
        for key, value in info.items():
            value = np.asarray(value)
            if key in out:
                out[key] = np.where(mask, value, out[key])
                out[f"_{key}"] = out[f"_{key}"] | mask
            else:
                out[key] = np.where(mask, value, np.zeros((), value.dtype)).astype(value.dtype)
                out[f"_{key}"] = mask.copy()
    return out


# ----------------------------------------------------------------------------- evaluation and benchmark


def evaluate_lqr(
    oracle: bool,
    *,
    num_envs: int = 4,
    n_steps: int | None = None,
    seed: int = 0,
    **options: Any,
) -> dict[str, float]:
    """Fly the built-in LQR (residual action 0) for one episode per world; returns error statistics.

    oracle: True -> the LQR subtracts the true mean field (env option predictor="oracle").
    num_envs: worlds (seeds seed .. seed + num_envs - 1); the same seeds give the same
        episodes and noise with and without the oracle.
    n_steps: env steps per episode (default: DEFAULT_MAX_EPISODE_STEPS).
    options: further env options (reference, separation, control_hz, field knobs, ...).

    Returns pos_err_3d_mean (m), vel_err_3d_mean (m/s), pos_err_3d_peak (m),
    return_mean (episode reward), terminated (episodes ended early), env_steps.
    """
    options = {**options, "action_mode": "residual", "predictor": "oracle" if oracle else "none"}
    n_steps = DEFAULT_MAX_EPISODE_STEPS if n_steps is None else int(n_steps)
    env = DownwashFollowerVectorEnv(num_envs, max_episode_steps=n_steps, **options)
    env.reset(seed=seed)
    zeros = np.zeros((num_envs, 3), np.float32)
    alive = np.ones(num_envs, bool)
    pos, vel, peak, ret = [], [], np.zeros(num_envs), np.zeros(num_envs)
    terminated_any = np.zeros(num_envs, bool)
    for _ in range(n_steps):
        _, reward, term, trunc, info = env.step(zeros)
        pos.append(info["position_error"][alive])
        vel.append(info["velocity_error"][alive])
        peak = np.where(alive, np.maximum(peak, info["position_error"]), peak)
        ret += np.where(alive, reward, 0.0)
        terminated_any |= alive & term
        alive &= ~(term | trunc)
        if not alive.any():
            break
    env.close()
    return {
        "pos_err_3d_mean": float(np.concatenate(pos).mean()),
        "vel_err_3d_mean": float(np.concatenate(vel).mean()),
        "pos_err_3d_peak": float(peak.max()),
        "return_mean": float(ret.mean()),
        "terminated": int(terminated_any.sum()),
        "env_steps": int(sum(len(p) for p in pos)),
    }


def _best_rate(fn: Callable[[], int], repeats: int) -> float:
    best = 0.0
    for _ in range(repeats):
        t0 = time.perf_counter()
        n = fn()
        best = max(best, n / (time.perf_counter() - t0))
    return best


def env_steps_per_s_single(n_steps: int = 2000, *, repeats: int = 3, seed: int = 0, **options: Any) -> float:
    """Env steps per wall second of one `gymnasium.make("DownwashFollower-v0")` (with its
    wrappers), random actions, resets included; the best of `repeats` runs."""
    env = gym.make("DownwashFollower-v0", **options)
    env.action_space.seed(seed)
    env.reset(seed=seed)
    env.step(env.action_space.sample())  # warm-up

    def run() -> int:
        for _ in range(n_steps):
            _, _, term, trunc, _ = env.step(env.action_space.sample())
            if term or trunc:
                env.reset()
        return n_steps

    rate = _best_rate(run, repeats)
    env.close()
    return rate


def env_steps_per_s_vector(num_envs: int = 64, n_steps: int = 200, *, repeats: int = 3, seed: int = 0,
                           **options: Any) -> float:
    """Env steps (summed over worlds) per wall second of the native vector env
    (`gymnasium.make_vec(..., vectorization_mode="vector_entry_point")`), random actions,
    autoresets included; the best of `repeats` runs."""
    envs = gym.make_vec("DownwashFollower-v0", num_envs=num_envs, vectorization_mode="vector_entry_point", **options)
    envs.action_space.seed(seed)
    envs.reset(seed=seed)
    envs.step(envs.action_space.sample())  # warm-up

    def run() -> int:
        for _ in range(n_steps):
            envs.step(envs.action_space.sample())
        return n_steps * num_envs

    rate = _best_rate(run, repeats)
    envs.close()
    return rate
