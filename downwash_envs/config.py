"""The follower envs' options: `FollowerConfig`, its allowed values and its validation.

Every field of `FollowerConfig` is a `gymnasium.make` keyword. `make_config` turns
keyword options into a validated config: an unknown name raises TypeError listing
the allowed ones, a bad value `downwash_core.errors.ConfigError` (a ValueError) naming the
option and its allowed range, before anything is built. Numeric options refuse strings and
bools ("0.6", True): float() would read them as numbers.
Those checks, shared with the swarm's options, are `downwash_envs.option_checks`' (re-exported here).
"""

from __future__ import annotations

import copy
import dataclasses
import inspect
import weakref
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any, Mapping

import numpy as np

from controllers.lqr import LQRConfig
from downwash_core.errors import ConfigError
from downwash_core.params import LEADER_POSITION, SEPARATION_RANGE
from downwash_core.validate import choice, count, number, pair
from downwash_envs.option_checks import check_not_text_or_bool, number_option, pair_option, unknown_options_error
from sim.field import DownwashField, check_field
from sim.field_memory import is_stateful_field
from sim.observer import DEFAULT_BANDWIDTH, DisturbanceObserver
from sim.predictor import ZeroPredictor
from sim.fields.registry import FIELDS, field_parameters, resolve_field_spec
from sim.simulator import SimConfig
from sim.turbulence import OUTurbulence
from downwash_trajectories import REFERENCE_KWARGS as _SHAPED_REFERENCE_KWARGS
from downwash_trajectories import make_reference, random_passes

__all__ = [
    "ACTION_MODES", "ENV_REFERENCES", "ENV_REFERENCE_KWARGS", "PREDICTORS", "CONTROL_HZ_ALLOWED",
    "DEFAULT_ACTION_BOUND", "MAX_ACTION_BOUND", "MIN_FOLLOWER_HEIGHT", "DEFAULT_MAX_EPISODE_STEPS",
    "FIELD_RANDOMIZABLE", "DEFAULT_FIELD_RANDOMIZATION", "MASS_SCALE_RANGE", "FIELD_SCALE_RANGE",
    "FIELD_KNOBS", "REWARD_WEIGHTS", "REFERENCE_LIMITS", "VEHICLE_RANDOMIZABLE", "VEHICLE_SPREAD_MAX",
    "FollowerConfig", "make_config", "build_field", "randomizable_constants", "unknown_options_error",
]  # fmt: skip

ACTION_MODES = ("residual", "acceleration")
PREDICTORS = ("none", "oracle", "dob")
# the outer loops an env flies: the paper's LQR, the LQR with integral action (controllers.integral), and the
# controllers labs fly (controllers.crazyflie, controllers.indi); each at the env's control rate
CONTROLLERS = ("lqr", "integral", "mellinger", "pid", "indi")
DEFAULT_ACTION_BOUND = MappingProxyType({"residual": 5.0, "acceleration": 10.0})  # m/s^2, per axis
MAX_ACTION_BOUND = 20.0  # m/s^2, largest accepted action_bound
# Hz, controller (= env step) rates offered; those dividing the autopilot grid (100 Hz
# with the default downwash_core.params.RATES: all of them) are accepted.
CONTROL_HZ_ALLOWED = (10, 20, 25, 50, 100)
MIN_FOLLOWER_HEIGHT = 0.3  # m, the lowest reference height a leader position / separation may give
DEFAULT_MAX_EPISODE_STEPS = 500  # env steps (10 s at 50 Hz)

# Shape parameters each reference accepts in `reference_kwargs`: those of
# `downwash_trajectories.make_reference`, plus "passes" (per-episode `random_passes` patterns), whose
# parameters are random_passes' keywords except those the env sets itself.
_PASSES_SET_BY_ENV = ("rng", "n_worlds", "center", "depth_range", "n_segments", "start")
ENV_REFERENCE_KWARGS = MappingProxyType({
    # the follower's paths beneath a hovering leader (the moving-leader references are not for it)
    **{name: _SHAPED_REFERENCE_KWARGS[name] for name in ("hover", "lemniscate", "transect")},
    "passes": tuple(p for p in inspect.signature(random_passes).parameters if p not in _PASSES_SET_BY_ENV),
})
ENV_REFERENCES = tuple(ENV_REFERENCE_KWARGS)  # hover, lemniscate, transect, passes
# Limits on the reference's shape, so that the observation bounds are never reached.
REFERENCE_LIMITS = MappingProxyType({"extent": 5.0, "speed": 5.0, "acc": 10.0})  # m from below the leader, m/s, m/s^2

# DownwashField constants that domain randomisation may scale (the fade edges are left out:
# scaling them independently could invert the smoothstep).
FIELD_RANDOMIZABLE = (
    "strength", "strength_depth", "width0", "width_slope", "approach_gain", "approach_speed",
    "radial_gain", "radial_offset", "radial_speed_gain", "radial_speed", "leader_speed_scale",
)
DEFAULT_FIELD_RANDOMIZATION = MappingProxyType(
    {"strength": (0.7, 1.3), "width0": (0.8, 1.2), "width_slope": (0.8, 1.2)}
)
MASS_SCALE_RANGE = (0.5, 1.5)  # -, allowed true-mass factors (thrust-to-weight 2.3 stays > 1.5)
FIELD_SCALE_RANGE = (0.1, 5.0)  # -, allowed field-constant factors
# Vehicle parameters that `randomize` may scale per episode, in the order they are drawn, and the
# largest relative spread (a factor in [0.5, 1.5], as MASS_SCALE_RANGE).
VEHICLE_RANDOMIZABLE = ("mass", "inertia", "motor_lag")
VEHICLE_SPREAD_MAX = 0.5  # -, relative
FIELD_KNOBS = ("c4_amplitude", "swirl", "skew")  # DownwashField's misspecification knobs
REWARD_WEIGHTS = ("alive_reward", "position_cost_weight", "velocity_cost_weight", "action_cost_weight",
                  "action_rate_cost_weight", "termination_penalty")


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
            `downwash_trajectories`: hover {offset (3,) m from the point below the
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
        predictor: "none", "oracle" (the LQR subtracts the true mean field,
            evaluated at 45 Hz; residual mode only), "dob" (a disturbance observer,
            `sim.observer.DisturbanceObserver`, at the bandwidth chosen for the env's controller: the generic
            baseline a learned compensation is compared with), or a predictor object
            (`sim.predictor.Predictor`, e.g. a learned model behind the guard:
            ``GuardedPredictor(LearnedPredictor.from_checkpoint(path))`` of
            `downwash.guard` and `downwash.predictor`), copied into each env.
    Downwash field
        c4_amplitude, swirl, skew: the field's misspecification knobs (see
            `sim.field.DownwashField`); all 0 by default.
        field: a field object with `DownwashField`'s call signature, or a field spec
            string: a registered name ("so2", "so2-c4", "so2-swirl", "so2-skew",
            "momentum"), optionally with parameters ("momentum:thrust_scale=1.5"), or
            "MODULE:FACTORY" (see docs/fields.md). The knobs need a `DownwashField`.
        field_randomization: None, "default" (so2: strength x U(0.7, 1.3), width0 and
            width_slope x U(0.8, 1.2)) or {constant: (low, high)} factors drawn per
            episode per world, in 0.1-5, on constants of `randomizable_constants(field)`
            (so2's FIELD_RANDOMIZABLE; the float constants of momentum, jet, pybullet, fitted:).
        mass_randomization: None or (low, high): the follower's true mass (and
            inertia) scaled by a factor drawn per episode, within 0.5-1.5. The
            controller keeps the nominal mass.
        randomize: None or {parameter: spread}: each agent's true vehicle parameters scaled
            per episode by factors drawn from U(1 - spread, 1 + spread), spreads in
            [0, 0.5], drawn from the env's generator after every other draw (so the other
            draws are those of an env without it): "mass" (the body's mass, and its
            inertia with it, as mass_randomization), "inertia" (a further factor on the
            inertia alone), "motor_lag" (every rotor's first-order time constant). The
            controller keeps the nominal vehicle. Off by default; not with mass_randomization.
    Termination and reward
        max_tracking_error: m, the tracking box: an episode terminates when the
            follower's true position is farther than this from its reference
            (allowed (0, 5]); also on collision or divergence.
        alive_reward, position_cost_weight, velocity_cost_weight, action_cost_weight,
            action_rate_cost_weight, termination_penalty: reward weights, >= 0 (see
            `DownwashFollowerEnv`).
    Other
        sim_config: `sim.simulator.SimConfig` (vehicle, rates, motion-capture noise,
            failure checks); its controller rate is replaced by control_hz.
        lqr: `controllers.lqr.LQRConfig` (LQR weights, tilt limit) of every vehicle's
            outer loop; default the paper's.
        controller: every vehicle's outer loop: "lqr" (default, the paper's), "integral"
            (the LQR with integral action on the position error, `controllers.integral`),
            or a controller labs fly, "mellinger", "pid" (the Crazyflie firmware's) or
            "indi"; each at control_hz. `lqr` sets the weights of the first two only.
        turbulence: `sim.turbulence.OUTurbulence` (intensity, correlation time);
            default 10 % and 0.05 s.
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
    predictor: Any = "none"
    controller: str = "lqr"
    c4_amplitude: float = 0.0
    swirl: float = 0.0
    skew: float = 0.0
    field: Any = None
    field_randomization: str | Mapping[str, tuple[float, float]] | None = None
    mass_randomization: tuple[float, float] | None = None
    randomize: Mapping[str, float] | None = None
    max_tracking_error: float = 1.0
    alive_reward: float = 1.0
    position_cost_weight: float = 2.0
    velocity_cost_weight: float = 0.5
    action_cost_weight: float = 0.05
    action_rate_cost_weight: float = 0.05
    termination_penalty: float = 50.0
    sim_config: SimConfig | None = None
    lqr: LQRConfig | None = None
    turbulence: OUTurbulence | None = None
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
        """m, (low, high) separation below the leader (equal for a fixed separation)."""
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

    @property
    def vehicle_spreads(self) -> dict[str, float]:
        """{parameter: relative spread} of `randomize`, in VEHICLE_RANDOMIZABLE order; empty when off."""
        r = self.randomize or {}
        return {k: float(r[k]) for k in VEHICLE_RANDOMIZABLE if k in r}

    @property
    def sim_base(self) -> SimConfig:
        """`sim_config`, or the default `SimConfig` (before control_hz is applied)."""
        return self.sim_config if self.sim_config is not None else SimConfig()


def make_config(options: Mapping[str, Any] | None = None) -> FollowerConfig:
    """A validated `FollowerConfig` from keyword options; unknown names raise TypeError."""
    options = dict(options or {})
    allowed = tuple(f.name for f in dataclasses.fields(FollowerConfig))
    unknown = sorted(set(options) - set(allowed))
    if unknown:
        raise unknown_options_error("the env", unknown, allowed)
    return FollowerConfig(**options)


def _separation_range(sep: Any) -> tuple[float, float]:
    lo, hi = SEPARATION_RANGE
    check_not_text_or_bool("separation", sep, f"a number in [{lo}, {hi}] m, or (low, high) within it")
    if np.ndim(sep) == 0:
        s = number("separation", sep, "m", lo, hi)
        return s, s
    return pair("separation", sep, "m", lo, hi)


def _control_hz_allowed(rates) -> tuple[int, ...]:
    autopilot_hz = 1.0 / rates.autopilot_dt
    return tuple(hz for hz in CONTROL_HZ_ALLOWED if abs(autopilot_hz / hz - round(autopilot_hz / hz)) < 1e-9)


def _validate(c: FollowerConfig) -> None:
    """Check every option; raise ConfigError naming the first bad one and what is allowed."""
    choice("action_mode", c.action_mode, ACTION_MODES)
    if c.action_bound is not None:
        number_option("action_bound", c.action_bound, "m/s^2", 0.0, MAX_ACTION_BOUND, lo_open=True)
    choice("reference", c.reference, ENV_REFERENCES)
    if c.reference_kwargs is not None:
        if not isinstance(c.reference_kwargs, Mapping):
            raise ConfigError(f"reference_kwargs: expected a dict, got {type(c.reference_kwargs).__name__}")
        unknown = sorted(set(c.reference_kwargs) - set(ENV_REFERENCE_KWARGS[c.reference]))
        if unknown:
            raise ConfigError(
                f"reference_kwargs: unknown {unknown} for reference {c.reference!r}; "
                f"allowed: {', '.join(ENV_REFERENCE_KWARGS[c.reference])}"
            )
        lim = REFERENCE_LIMITS
        for k, v in c.reference_kwargs.items():  # every shape parameter is a number or numbers
            check_not_text_or_bool(f"reference_kwargs[{k!r}]", v, f"numbers (the {c.reference} reference checks "
                                   f"their ranges; its path must stay within {lim['extent']} m of the point below "
                                   f"the leader, {lim['speed']} m/s, {lim['acc']} m/s^2)")
    _validate_geometry(c)
    if not isinstance(c.random_phase, (bool, np.bool_)):
        raise ConfigError(f"random_phase: expected True or False, got {c.random_phase!r}")
    if not isinstance(c.sim_base, SimConfig):
        raise ConfigError(f"sim_config: expected a sim.simulator.SimConfig, got {type(c.sim_base).__name__}")
    if c.lqr is not None and not isinstance(c.lqr, LQRConfig):
        raise ConfigError(f"lqr: expected a controllers.lqr.LQRConfig, got {type(c.lqr).__name__}")
    choice("controller", c.controller, CONTROLLERS)
    if c.lqr is not None and c.controller not in ("lqr", "integral"):
        raise ConfigError(f"lqr: sets the LQR's weights; controller={c.controller!r} has its own gains "
                          "(allowed with controller 'lqr' or 'integral')")
    if c.turbulence is not None and not isinstance(c.turbulence, OUTurbulence):
        raise ConfigError(f"turbulence: expected a sim.turbulence.OUTurbulence, got {type(c.turbulence).__name__}")
    rates = c.sim_base.rates
    allowed_hz = _control_hz_allowed(rates)
    if isinstance(c.control_hz, bool) or c.control_hz not in allowed_hz:
        raise ConfigError(
            f"control_hz: got {c.control_hz!r}; allowed: {', '.join(map(str, allowed_hz))} Hz "
            f"(the controller runs on the {1.0 / rates.autopilot_dt:g} Hz autopilot grid)"
        )
    if isinstance(c.predictor, str):
        choice("predictor", c.predictor, PREDICTORS)
    elif not callable(c.predictor):
        raise ConfigError(f"predictor: expected one of {list(PREDICTORS)} or a predictor object (sim.predictor.Predictor, "
                          f"e.g. downwash.guard.GuardedPredictor(...)), got {type(c.predictor).__name__}")
    if not (isinstance(c.predictor, str) and c.predictor == "none") and c.action_mode != "residual":
        raise ConfigError(
            f"predictor: {c.predictor!r} only acts on the LQR command, which action_mode='acceleration' "
            "replaces; use action_mode='residual' or predictor='none'"
        )
    _validate_field(c)
    if c.mass_randomization is not None:
        pair_option("mass_randomization", c.mass_randomization, "(factor)", *MASS_SCALE_RANGE)
    _validate_randomize(c)
    number_option("max_tracking_error", c.max_tracking_error, "m", 0.0, 5.0, lo_open=True)
    for name in REWARD_WEIGHTS:
        number_option(name, getattr(c, name), "(reward weight)", 0.0, 1e6)
    count("render_width", c.render_width, 16, 640)  # pixels
    count("render_height", c.render_height, 16, 480)
    # Reference shape parameters: let the reference classes check them (they name the argument).
    _reference_probe(c)


def _validate_randomize(c: FollowerConfig) -> None:
    """`randomize`: known parameters, spreads in [0, VEHICLE_SPREAD_MAX], not beside mass_randomization."""
    r = c.randomize
    if r is None:
        return
    if not isinstance(r, Mapping):
        raise ConfigError(f"randomize: expected None or a dict {{parameter: spread}}, got {type(r).__name__}")
    unknown = sorted(set(r) - set(VEHICLE_RANDOMIZABLE))
    if unknown:
        raise ConfigError(f"randomize: unknown parameter(s) {unknown}; allowed: {', '.join(VEHICLE_RANDOMIZABLE)}")
    for k, v in r.items():
        number_option(f"randomize[{k!r}]", v, "(relative spread)", 0.0, VEHICLE_SPREAD_MAX)
    if c.mass_randomization is not None:
        raise ConfigError("randomize and mass_randomization: give one (randomize={'mass': s} draws the follower's "
                          "mass factor from U(1 - s, 1 + s))")


def _validate_geometry(c: FollowerConfig) -> None:
    """Separation and leader position: the reference must stay above MIN_FOLLOWER_HEIGHT."""
    _, sep_hi = _separation_range(c.separation)
    check_not_text_or_bool("leader_position", c.leader_position,
                           f"(x, y, z) m, z in [{MIN_FOLLOWER_HEIGHT} + separation, 20]")
    try:
        leader = np.array(c.leader_position, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(f"leader_position: expected (x, y, z) in m, got {c.leader_position!r}") from None
    if leader.shape != (3,) or not np.all(np.isfinite(leader)):
        raise ConfigError(f"leader_position: expected 3 finite numbers (m), got {c.leader_position!r}")
    if not (leader[2] - sep_hi >= MIN_FOLLOWER_HEIGHT and leader[2] <= 20.0):
        raise ConfigError(
            f"leader_position: z = {leader[2]} m with separation up to {sep_hi} m puts the reference below "
            f"{MIN_FOLLOWER_HEIGHT} m; allowed z in [{MIN_FOLLOWER_HEIGHT} + separation, 20] m"
        )


def randomizable_constants(field: Any) -> tuple[str, ...]:
    """The constants `field_randomization` may scale: FIELD_RANDOMIZABLE for a `DownwashField` (`fitted:` ones
    too), the float constants of any other stateless dataclass field (momentum, jet, pybullet, `fitted:`), else ()."""
    if isinstance(field, DownwashField):
        return FIELD_RANDOMIZABLE
    if not dataclasses.is_dataclass(field) or isinstance(field, type) or is_stateful_field(field):
        return ()
    kinds, names = field_parameters(type(field)), [f.name for f in dataclasses.fields(field) if f.init]
    return tuple(k for k in names if kinds[k] is float and type(getattr(field, k)) is not bool
                 and isinstance(getattr(field, k), (float, int, np.floating)))


def _validate_field(c: FollowerConfig) -> None:
    """The field knobs, field randomisation, and a custom field."""
    number_option("c4_amplitude", c.c4_amplitude, "-", -0.99, 0.99)
    number_option("swirl", c.swirl, "-", -10.0, 10.0)
    number_option("skew", c.skew, "s/m", 0.0, 10.0)
    knobs = any(float(getattr(c, k)) != 0.0 for k in FIELD_KNOBS)
    fr = c.field_randomization
    if fr is not None and not (isinstance(fr, Mapping) or (isinstance(fr, str) and fr == "default")):
        raise ConfigError(f"field_randomization: got {fr!r} (a {type(fr).__name__}); allowed: None, 'default' or "
                          "a dict {constant: (low, high)}")
    field = build_field(c.field)  # (None: the default DownwashField)
    if c.field is not None:
        check_field(field, name="field")  # shape and finiteness, once, before any episode
    if knobs and not isinstance(field, DownwashField):
        raise ConfigError(f"field: c4_amplitude/swirl/skew need a sim.field.DownwashField, got {type(field).__name__}")
    if fr is None:
        return
    what, allowed = type(field).__name__, randomizable_constants(field)
    if not allowed:
        raise ConfigError(f"field_randomization: needs a field of float dataclass constants (so2, momentum, jet, "
                          f"pybullet, fitted:PATH of one), got {what}")
    if isinstance(fr, str) and not isinstance(field, DownwashField):
        raise ConfigError(f"field_randomization: 'default' scales so2's constants; for a {what} give "
                          f"{{constant: (low, high)}} factors of: {', '.join(allowed)}")
    fr = DEFAULT_FIELD_RANDOMIZATION if isinstance(fr, str) else fr
    unknown = sorted(set(fr) - set(allowed), key=str)
    if unknown:
        raise ConfigError(f"field_randomization: {unknown}: not among {what}'s randomizable float constants; "
                          f"allowed: {', '.join(allowed)}")
    for k, v in fr.items():
        pair_option(f"field_randomization[{k!r}]", v, "(factor)", *FIELD_SCALE_RANGE)
    scaled = {k: (float(getattr(field, k)), r) for k, r in c.field_scales.items()}
    for k, (value, r) in scaled.items():  # the field's own checks, at both ends of every range
        if value == 0.0:
            raise ConfigError(f"field_randomization[{k!r}]: {what}.{k} is 0, which no factor changes; allowed: "
                              f"nonzero constants of {', '.join(allowed)}")
        for factor in r:
            try:
                dataclasses.replace(field, **{k: value * factor})
            except ConfigError as e:
                raise ConfigError(f"field_randomization[{k!r}]: factor {factor:g} makes {k} = {value * factor:g}, "
                                  f"which {what} refuses: {e}") from None
    if not isinstance(field, DownwashField):  # every constant at its low, then its high factor: finite forces
        for end in (0, 1):
            check_field(dataclasses.replace(field, **{k: v * r[end] for k, (v, r) in scaled.items()}),
                        name=f"field_randomization ({('low', 'high')[end]} factors)")


def build_field(field: Any) -> Any:
    """The field object of the `field` option (ConfigError when it names none).

    None: the default `DownwashField()`; a string: a field spec of the registry
    (`"momentum"`, `"so2-c4"`, `"so2:strength=8"`, or `"MODULE:FACTORY"`; see
    `sim.fields.registry`); otherwise the object itself, which must be callable.
    """
    if field is None:
        return DownwashField()
    if isinstance(field, str):
        return resolve_field_spec(field, label="field")
    if not callable(field):
        raise ConfigError(
            f"field: expected a callable field(p_a, v_a, R_a, p_b, v_b) or a registered name "
            f"({', '.join(FIELDS)}), got {type(field).__name__}"
        )
    return field


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
            number("reference_kwargs['duration']", kw["duration"], "s", 0.0, 1e5, lo_open=True)
        defaults = inspect.signature(random_passes).parameters
        get = lambda k: float(kw.get(k, defaults[k].default))  # noqa: E731
        extent = max(get("max_offset") + get("pass_half_length"), get("hover_radius"))
        if extent > lim["extent"]:
            raise ConfigError(
                f"reference_kwargs: passes reach {extent:g} m from the wake axis "
                f"(max_offset + pass_half_length, hover_radius); allowed up to {lim['extent']} m"
            )
        return  # speeds are limited to 1 m/s by random_passes
    n = 257  # sample times over one period, as worlds of one batched reference
    ref = make_reference(c.reference, center, n, **kw)
    sample = ref(np.linspace(0.0, float(np.max(getattr(ref, "period", 1.0))), n))
    extent = float(np.max(np.linalg.norm(sample.pos - center, axis=-1)))
    speed = float(np.max(np.linalg.norm(sample.vel, axis=-1)))
    acc = float(np.max(np.linalg.norm(sample.acc, axis=-1)))
    if extent > lim["extent"] or speed > lim["speed"] or acc > lim["acc"]:
        raise ConfigError(
            f"reference_kwargs {kw}: the {c.reference} reaches {extent:.3g} m from the point below the "
            f"leader, {speed:.3g} m/s, {acc:.3g} m/s^2; allowed up to {lim['extent']} m, "
            f"{lim['speed']} m/s, {lim['acc']} m/s^2"
        )


def predictor_of(spec: Any, oracle: Any, owner: Any, bandwidth: float = DEFAULT_BANDWIDTH) -> Any:
    """The predictor an env's ``predictor`` option names: no model for "none", ``oracle()`` for
    "oracle", else the owner's own disturbance observer ("dob", at `bandwidth`: the one chosen for the
    env's controller, `sim.observer.bandwidth_for`) or deep copy of the given predictor object (made
    once: a predictor with state, such as a guard or the observer, serves one simulator)."""
    if isinstance(spec, str) and spec != "dob":
        return oracle() if spec == "oracle" else ZeroPredictor()
    own = _OWN_PREDICTORS.get(owner)
    if own is None:
        own = _OWN_PREDICTORS[owner] = (DisturbanceObserver(bandwidth=bandwidth) if spec == "dob"
                                        else copy.deepcopy(spec))
    return own


_OWN_PREDICTORS: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()  # owner -> its own predictor (predictor_of)
