"""The multi-rate stepping loop: physics, autopilot, field, wind, motion capture, controller, predictor.

Rates (downwash_core.params.Rates): physics 500 Hz; autopilot, downwash field, wind and motion
capture on the 100 Hz autopilot grid; the LQR at 50 Hz; the predictor at 45 Hz,
evaluated at the first autopilot tick after each 1/45 s and held in between.

Everything is batched over worlds W and vehicles V. Each world draws its noise (motion capture, turbulence)
from its own generator, and its wind gusts from a second one of its own (`default_rng([seed, WIND_STREAM])`),
so a world's flight does not depend on which other worlds share its batch: the batched loop equals a loop of
single flights bit for bit (a test), and a flight without wind draws what it drew before wind existed.

The loop is assembled from components, each injected and each with its config in its own module: the sensor
(`SimConfig.mocap`, `sim.sensors`: motion capture and its per-episode offsets, drawn at reset from a third
stream of the world's, `SENSOR_STREAM`), the `controller` (`controllers.lqr.FeedbackLinearisedLQR`), the
`autopilot` (`controllers.autopilot.Autopilot`), the `turbulence` (`sim.turbulence.OUTurbulence`), the
downwash `field` (`sim.field.DownwashField` or any object with its call signature), how wakes combine
(`aggregation`, `sim.aggregation`), the ambient `wind` (`sim.wind.DrydenWind`), the `predictor`
(`sim.predictor`) and, optionally, the `safety` filter on the commanded accelerations (`sim.safety`: None
flies as without it, bit for bit).

Ambient wind (`wind=DrydenWind(...)`; None or an `off` wind leave the loop and its logs bit for bit as without
it): u_air = mean + gust, ONE gust state (3, 2) per world, shared by its vehicles (the Dryden scale lengths,
3-23 m here, dwarf the ~1 m between them; `sim.wind`), advanced on the autopilot grid by the exact sampled
recursion. It acts on every vehicle through the airframe drag (`sim.wind.drag_acceleration`) and convects the
wakes: the field sees velocities relative to the air, v - u_air (exact Galilean invariance for a uniform
wind), as does the oracle; learned predictors see the estimated ground velocities. Logged rows then hold
`wind` (m/s) and `wind_acc` (the drag). A field with memory (`sim.field_memory`) is stepped on the autopilot
grid, carried by the same air, and a predictor with state (`sim.predictor.is_stateful`) is reset with its
worlds and told which are due: both on the readable path. A controller with ``reset(worlds)`` (its integrators
and filters, `controllers.lab_common`) is reset with its worlds too.

Two paths, one behaviour, over the modules below this one: `sim.passes` (the compiled passes of one autopilot
tick, shared by both paths), `sim.fused` (the fused tick: a whole controller tick as ONE compiled call, one
variant with and one without the wind passes), `sim.plan` (whether the components can fly it, `make_plan`,
and its bound tables, `Plan`) and `sim.rows` (a tick's log row: a `Row` on the fused path, a dict on the
other). The readable path (`_tick_readable`, of `sim.ticks.ReadableTicks`) runs each autopilot tick as the
passes around the pluggable Python calls (predictor, field, reference, controller); the fast path
(`_tick_fused`, of `sim.ticks.FusedTicks`, when `make_plan` finds a compiled form for every component) calls
the fused kernel, with a batch's worlds in chunks for this thread and its helper threads (`sim.fork_join`). The plan is rebuilt when a component is replaced (assigning the
attribute does). tests/test_fast_path.py checks that both paths fly bit-identical logs.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Sequence

import numpy as np

from controllers.autopilot import Autopilot
from controllers.lqr import FeedbackLinearisedLQR
from downwash_core.errors import ConcurrentUseError, ConfigError
from downwash_core.jit import announce_first_compile, mark_compiled
from downwash_core.params import QUAD, RATES, QuadParams, Rates
from downwash_core.provenance import describe
from downwash_core.state import VehicleStates
from downwash_core.status import Status
from sim.field_memory import kept_memory, memory_oracle
from sim.estimation import MocapKalmanFilter
from sim.field import DownwashField, check_field
from sim.passes import Sensed, status_kernel, true_states_kernel
from sim.physics import check_world_memory, make_physics, profiling_timer_off
from sim.plan import PlanInputs, flies_compiled_controller, make_plan
from sim.predictor import Predictor, ZeroPredictor, is_stateful
from sim.safety import SafetyConfig, safety_filter
from sim.scene import Scene
from sim.sensor_contract import compiled_sensor_law, episode_state
from sim.sensors import MocapConfig, check_sensor, draw_episode_offset
from sim.ticks import FusedTicks, ReadableTicks, as_batch
from sim.turbulence import OUTurbulence
from sim.vehicle_params import VehicleParams, scene_field, scene_predictor
from sim.wind import DrydenWind

__all__ = ["SimConfig", "Simulator", "WIND_STREAM"]

WIND_STREAM = 0x57494E44  # "WIND": world w's gusts come from default_rng([seed_w, WIND_STREAM])
# The fused path's physics steps per second over the readable path's, one world, the same flight
# (experiments.benchmark.closed_loop_sim, fast=True vs False; zero or oracle predictor): medians of 2.0-2.3x.
_READABLE_SLOWDOWN = "2x"
log = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimConfig:
    """The vehicle, the rates, the sensor and the failure checks of a flight.

    quad: the vehicle of a scene without kinds; a scene's vehicles of kinds (`build_scene(kinds=...)`,
    the paper quad by default) fly each its own kind's numbers (`sim.vehicle_params`).
    mocap: the sensor, any of `sim.sensors` (`MocapConfig()`, `BiasedMocap(...)`, `make_sensor(name)`).
    The controller, autopilot, turbulence, field, wind and predictor are components of
    the `Simulator`, each with its own settings.
    """

    rates: Rates = field(default_factory=lambda: RATES)
    quad: QuadParams = field(default_factory=lambda: QUAD)
    mocap: Any = field(default_factory=MocapConfig)  # a `sim.sensors.Sensor`
    ground_clearance: float = 0.03  # m, a vehicle centre below this height has hit the ground
    collision_radius_xy: float = 0.26  # m, paper quads closer than this laterally (other kinds: by size, per pair) ...
    collision_radius_z: float = 0.08  # m, ... and vertically (ellipsoid) have collided
    max_distance: float = 100.0  # m, beyond this from the origin the flight has diverged
    noise_block: int = 256  # autopilot ticks of noise drawn per generator call

    def to_dict(self) -> dict[str, Any]:
        out = asdict(self)
        if type(self.mocap) is not MocapConfig:  # another sensor: named (the default's record stays as it was)
            out["mocap"] = describe(self.mocap)
        return out




# Assigning one of these attributes of a Simulator rebinds its compiled passes at the next tick
# (its components, and the state arrays the passes address, which are meant to be updated in place).
_BOUND_INPUTS = frozenset({"field", "predictor", "controller", "autopilot", "turbulence", "wind", "aggregation",
                           "field_enabled", "fast", "safety", "t", "tick_index", "active", "pos_est", "vel_est", "turb",
                           "gust_state", "f_hat", "next_prediction", "mocap_offset"})


class Simulator(FusedTicks, ReadableTicks):
    """W worlds of V vehicles flying the full stack; advance one controller tick at a time.

    reference: callable t (W,) -> RefSample with (W, V, ...) arrays (`downwash_trajectories.stack`).
    seeds: one int per world; a world's noise comes only from its own generators.
    config: `SimConfig` (vehicle, rates, the sensor `mocap`, failure checks).
    Each vehicle flies its kind's numbers, and each pair's wake scales with its two kinds
    (`sim.vehicle_params`: for the field and an oracle predictor alike).
    Components (each defaults to the paper's):
      controller: the outer loop, `FeedbackLinearisedLQR(LQRConfig(...))` or any object
        with its `command_setpoint(state, ref, f_hat, out, residual, override, lookahead)`;
      autopilot: `Autopilot(quad, ...)` (its attitude loop, for each vehicle through `Autopilot.tables`);
      turbulence: `OUTurbulence(intensity, time_constant)`;
      field: any object with the `DownwashField` call signature;
      aggregation: how the wakes of several leaders combine on a vehicle, passed to
        `sim.aggregation.wake_field` (None: linear superposition, `pairwise_field`);
      wind: `sim.wind.DrydenWind` (mean wind + Dryden gusts) or None (see the module
        docstring: one gust state per world, drag on every vehicle, wakes convected);
      predictor: `sim.predictor.Predictor`, evaluated at 45 Hz and held;
      safety: `sim.safety.SafetyConfig` or None, the CBF filter on the commanded accelerations (`sim.safety`).
    field_enabled: (W,) bool, False for worlds flown without downwash.
    fast: take the fused compiled path when every component has a compiled form (the
      result is the same bit for bit; False forces the readable path).
    The fused path flies when every component has a compiled form (`sim.plan` lists them;
    docs/extending.md). Anything else flies the readable path, the same loop with Python calls
    between the compiled passes (the same bits where both apply), about 2x slower for one
    world. With fast=True a controller without a compiled form is named in one logged warning.
    Components may be replaced between ticks (attributes of the same names); arrays such
    as `field_enabled`, `t` or `active` are updated in place only.
    """

    def __init__(
        self,
        scene: Scene,
        reference: Callable,
        seeds: Sequence[int],
        *,
        config: SimConfig | None = None,
        controller: Any | None = None,
        autopilot: Autopilot | None = None,
        turbulence: OUTurbulence | None = None,
        field: Any | None = None,
        predictor: Predictor | None = None,
        field_enabled: np.ndarray | None = None,
        n_threads: int = 0,
        wind: DrydenWind | None = None,
        aggregation: Any = None,
        fast: bool = True,
        safety: SafetyConfig | None = None,
    ):
        object.__setattr__(self, "_bound", False)
        object.__setattr__(self, "_in_use", threading.RLock())  # one thread at a time (`_one_thread`)
        if wind is not None and not isinstance(wind, DrydenWind):
            raise ConfigError(f"wind: expected a sim.wind.DrydenWind or None, got {type(wind).__name__}")
        self.scene = scene
        self.cfg = cfg = config if config is not None else SimConfig()
        self.vehicle_params = vp = VehicleParams.of(scene, cfg)  # each vehicle's own numbers (sim.vehicle_params)
        self.sensor = check_sensor(cfg.mocap)  # SimConfig.mocap, the sensor (`sim.sensors`)
        self.reference = reference
        self.controller = controller if controller is not None else FeedbackLinearisedLQR()
        self.autopilot = autopilot if autopilot is not None else Autopilot(cfg.quad)
        self.turbulence = turbulence if turbulence is not None else OUTurbulence()
        self.field = field if field is not None else DownwashField()
        self.predictor = predictor if predictor is not None else ZeroPredictor()
        self.aggregation, self.safety = aggregation, safety
        self.fast = bool(fast)
        seeds = [int(s) for s in seeds]
        W, V = len(seeds), scene.n_vehicles
        if W < 1:
            raise ConfigError("seeds: expected one seed per world, got none")
        self.W, self.V = W, V
        self.seeds = seeds
        self.field_enabled = np.ones(W, bool) if field_enabled is None else np.asarray(field_enabled, bool)
        if self.field_enabled.shape != (W,):
            raise ConfigError(f"field_enabled: expected shape ({W},), got {self.field_enabled.shape}")

        r = cfg.rates
        check_world_memory(W, V, name="worlds")  # before MuJoCo's batch and the state arrays are allocated
        self.physics = make_physics(scene.model, W, n_threads)
        self.kf = MocapKalmanFilter(r.autopilot_dt, self.sensor)  # its measurement noise is the sensor's
        self.mass = vp.mass[:, None]  # (V, 1) kg: (W, V, 3) accelerations times this are forces

        # index arrays, resolved once
        qa, va = scene.qpos_adr, scene.qvel_adr
        self._pos_idx = qa[:, None] + np.arange(3)
        self._quat_idx = qa[:, None] + 3 + np.arange(4)
        self._vel_idx = va[:, None] + np.arange(3)
        # per vehicle: qpos address, qvel address, body id, 4 actuator ids (columns _QPOS.._ACT)
        self._layout = np.concatenate(
            [np.stack([qa, va, scene.body_ids], axis=1), scene.act_ids], axis=1
        ).astype(np.int64)
        # scalars of the hot loop that do not depend on the components, as Python floats
        self._prediction_period = 1.0 / r.predictor_hz  # s
        self._sensor_law = compiled_sensor_law(self.sensor, W, V)  # a law outside the family (sim.sensor_contract)
        self._sigma_p, self._sigma_att = self.sensor.compiled() if self._sensor_law is None else (0.0, 0.0)
        self._kf_gain_p, self._kf_gain_v = (float(g) for g in self.kf.gain)
        self._drag_gain = vp.drag_gain  # (V,) 1/m, of the wind's drag

        # per-world state beyond MuJoCo's; pos_est, vel_est, turb, gust_state, f_hat, t,
        # tick_index and next_prediction are updated in place (copy to keep a value; the
        # rows tick() returns are fresh already)
        self.t = np.zeros(W)  # s, time since each world's reset
        self.tick_index = np.zeros(W, np.int64)
        self.status = np.zeros(W, np.int64)
        self.message = [""] * W
        self.active = np.ones(W, bool)
        self.pos_est = np.zeros((W, V, 3))  # m, Kalman estimate (prior for the next sample)
        self.vel_est = np.zeros((W, V, 3))  # m/s
        self.turb = np.zeros((W, V, 3))  # -, Ornstein-Uhlenbeck turbulence state
        self.mocap_offset = np.zeros((W, V, 3))  # m, the sensor's position offsets this episode
        self.gust_state = np.zeros((W, 3, 2))  # m/s, each world's Dryden gust state (zeros without wind)
        self.f_hat = np.zeros((W, V, 3))  # m/s^2, held prediction
        self.next_prediction = np.zeros(W)  # s
        self._rngs: list[np.random.Generator] = [None] * W  # type: ignore[list-item]
        self._wind_rngs: list[np.random.Generator | None] = [None] * W
        self._noise = np.zeros((W, cfg.noise_block, V, 9))  # per tick: mocap position, attitude, turbulence
        self._wind_noise = np.zeros((W, cfg.noise_block, 3, 2))  # per tick: the gusts' draws (wind on only)
        self._mass_believed = np.tile(vp.mass, (W, 1))  # (W, V) kg, the controller's model
        self._hover_controls = vp.hover_controls(scene.act_ids, self.physics.ctrl.shape[1])  # (nu,) N, at reset
        self._cursor = np.zeros(W, np.int64)
        self._cursor_max = 0  # max(self._cursor), kept as a Python int (no reduction per tick)
        self._due = np.zeros(W, bool)
        self._reused = Sensed.empty(W, V)  # buffers of the second and later autopilot ticks
        self._wind_reused = tuple(np.empty((W, V, 3)) for _ in range(3))  # air, vel_air, wind_acc, likewise
        self._rot_des = np.empty((W, V, 3, 3))  # body to world, set by the 50 Hz control
        self._yaw_rate_des = np.empty((W, V))  # rad/s
        self._thrust_acc = np.empty((W, V))  # m/s^2
        self._status_new = np.zeros(W, np.int64)
        self._ref_storage = (np.empty((3, W, V, 3)), np.empty((2, W, V)))  # a stacked reference's samples (vec, ang)
        self._ref_views = (*self._ref_storage[0], *self._ref_storage[1])  # pos, vel, acc, yaw, yaw_rate
        self.row: Mapping[str, np.ndarray] = {}
        self.wind = wind
        announce_first_compile()
        self._bind()
        self.reset(np.arange(W), seeds)
        if field is not None:  # once, before any step: a bad field is named, not found mid-batch
            start = self.true_states()
            check_field(field, start.pos, start.vel, start.rot, finite=False)

    def __setattr__(self, name: str, value: Any) -> None:
        if name == "wind" and "wind" in self.__dict__:  # its generators and gust states start at reset
            raise AttributeError("wind: set at construction (Simulator(..., wind=...)), not replaced afterwards")
        object.__setattr__(self, name, value)
        if name in _BOUND_INPUTS:
            object.__setattr__(self, "_bound", False)  # rebind at the next tick

    def _bind(self) -> None:
        """Bind the components' constants and the compiled passes' arguments (again after a change)."""
        cfg, r = self.cfg, self.cfg.rates
        self._wind_on = self.wind is not None and not self.wind.off
        self._ou_a, self._ou_b = self.turbulence.coefficients(r.autopilot_dt)
        self._ap_gain, self._max_thrust = self.vehicle_params.autopilot_tables(self.autopilot)  # (V, 14, 4), (V,) N
        self._scene_field = scene_field(self.field, self.vehicle_params)  # each pair with its kinds
        self._scene_predictor = scene_predictor(self.predictor, self.vehicle_params)
        self._memory = kept_memory(self.__dict__.get("_memory"), self.field, self.W, self.V, r.autopilot_dt,
                                   self.vehicle_params.names)
        self._scene_predictor = memory_oracle(self._memory, self._scene_predictor) or self._scene_predictor
        self._predictor_state = is_stateful(self._scene_predictor)
        self._safety_filter = safety_filter(self.safety, self.vehicle_params, self.controller, self.W, r.control_dt,
                                            self.__dict__.get("_safety_filter"))  # None: off; its estimates kept
        self._turbulence_intensity = float(self.turbulence.intensity)
        if self._wind_on:
            mean, sigma, length, axes, min_airspeed = self.wind.kernel_constants()
            self._wind_sense_consts = (axes, mean, self._drag_gain)
            self._wind_advance_consts = (r.autopilot_dt, mean, sigma, length, min_airspeed, np.zeros((3, 2, 2)),
                                         np.zeros((3, 2, 2)))
        # The readable path's compiled passes: their persistent arguments, bound once; every
        # array here is only ever updated in place, so each tick passes just the fresh ones.
        law = self._sensor_law  # (the family's stds, or the addresses of a compiled law: `sim.sensor_contract`)
        sample = (self._sigma_p, self._sigma_att) if law is None else (
            int(law.address), law.params.ctypes.data, law.state.ctypes.data)
        self._sense_args = (
            self.physics.qpos, self.physics.qvel, self._layout, self._noise, self._cursor, *sample,
            self.mocap_offset, self._kf_gain_p, self._kf_gain_v, self.pos_est, self.vel_est, self.t,
            self.next_prediction, self._due,
        )
        self._actuate_args = (
            self.field_enabled, self._noise, self._cursor, self.turb,
            self._ou_a, self._ou_b, self._turbulence_intensity, self.vehicle_params.mass, self.physics.xfrc_applied,
            self._layout, self.physics.qvel, self._rot_des, self._yaw_rate_des, self._thrust_acc, self._mass_believed,
            self._ap_gain, self._max_thrust, self.physics.ctrl,
            self.pos_est, self.vel_est, cfg.rates.autopilot_dt, self.t, self.active,
        )
        self._plan = make_plan(self, PlanInputs(**{k: getattr(self, "_" + k) for k in PlanInputs.names()})) if self.fast else None
        self._observe = None if getattr(self._plan, "monitors", False) else getattr(self._scene_predictor, "observe", None)
        if self.fast and not flies_compiled_controller(self.controller) and not self.__dict__.get("_warned_readable"):
            self.__dict__["_warned_readable"] = True  # once per simulator
            log.warning("Simulator: the controller %s has no compiled form (the fused tick runs "
                        "controllers.lqr.FeedbackLinearisedLQR and controllers with compiled_controller), so this "
                        "simulator flies the readable path, the same loop with the controller called from Python: "
                        "about %s slower (docs/extending.md, 'A new controller')", type(self.controller).__name__,
                        _READABLE_SLOWDOWN)
        object.__setattr__(self, "_bound", True)

    # ------------------------------------------------------------------ state access
    def true_states(self) -> VehicleStates:
        """The true states now (fresh arrays): positions (W, V, 3) m, velocities (W, V, 3) m/s
        (world frame, over the ground) and attitudes (W, V, 3, 3) body to world."""
        W, V = self.W, self.V
        pos, vel, rot = np.empty((W, V, 3)), np.empty((W, V, 3)), np.empty((W, V, 3, 3))
        true_states_kernel(self.physics.qpos, self.physics.qvel, self._layout, pos, vel, rot)
        return VehicleStates(pos, vel, rot)

    # ------------------------------------------------------------------ reset
    def reset(self, worlds: np.ndarray, seeds: Sequence[int] | None = None, reference: Callable | None = None) -> None:
        """Start the given worlds afresh at their reference's t = 0 state, hovering level (one
        thread at a time, as `tick`)."""
        lock = self._one_thread("reset")
        try:
            self._reset(worlds, seeds, reference)
        finally:
            lock.release()

    def _reset(self, worlds: np.ndarray, seeds: Sequence[int] | None, reference: Callable | None) -> None:
        worlds = np.asarray(worlds, dtype=np.int64)
        if reference is not None:
            self.reference = reference
        if seeds is not None:
            for w, s in zip(worlds, seeds):
                self.seeds[w] = int(s)
        if not self._bound:
            self._bind()
        ph = self.physics
        ph.reset(worlds)
        ref = self.reference(np.zeros(self.W))
        qpos, qvel = ph.qpos, ph.qvel
        for w in worlds:  # per-world python is fine here: resets are rare
            qpos[w, self._pos_idx] = ref.pos[w]
            half = 0.5 * ref.yaw[w]
            qpos[w, self._quat_idx] = np.stack([np.cos(half), 0 * half, 0 * half, np.sin(half)], axis=-1)
            qvel[w] = 0.0
            qvel[w, self._vel_idx] = ref.vel[w]
            ph.act[w] = self._hover_controls  # each vehicle's rotors at its own hover thrust
            ph.ctrl[w] = self._hover_controls
            ph.xfrc_applied[w] = 0.0
            self._rngs[w] = np.random.default_rng(self.seeds[w])
            if self._wind_on:  # the gusts start stationary, from the world's own wind stream
                self._wind_rngs[w] = np.random.default_rng([self.seeds[w], WIND_STREAM])
                self.gust_state[w] = self.wind.stationary_state(self._wind_rngs[w].standard_normal((3, 2)))
            else:
                self.gust_state[w] = 0.0
            self.mocap_offset[w] = draw_episode_offset(self.sensor, self.seeds[w], self.V)
            if self._sensor_law is not None:  # its memory, from the world's own sensor-state stream
                state = self._sensor_law.state
                state[w] = episode_state(self.sensor, self.seeds[w], self.V, state.shape[2])
            self._refill(w)
        self.t[worlds] = 0.0
        self.tick_index[worlds] = 0
        self.status[worlds] = Status.OK
        for w in worlds:
            self.message[w] = ""
        self.active[worlds] = True
        self.pos_est[worlds] = ref.pos[worlds]
        self.vel_est[worlds] = ref.vel[worlds]
        self.turb[worlds] = 0.0
        self.f_hat[worlds] = 0.0
        self.next_prediction[worlds] = 0.0
        for part in (self._memory, self._scene_predictor if self._predictor_state else None, self.controller,
                     self._safety_filter):
            if callable(getattr(part, "reset", None)):  # wakes, a predictor's, a controller's, the safety filter's state
                part.reset(worlds)
        self._cursor_max = int(self._cursor.max())

    def _refill(self, w: int) -> None:
        self._noise[w] = self._rngs[w].standard_normal(self._noise.shape[1:])
        if self._wind_on:
            self._wind_noise[w] = self._wind_rngs[w].standard_normal(self._wind_noise.shape[1:])
        self._cursor[w] = 0

    def _refill_used(self) -> None:
        """Refill the noise block of every world whose draws are used up (each from its own streams)."""
        for w in np.flatnonzero(self._cursor >= self._noise.shape[1]):
            self._refill(w)
        self._cursor_max = int(self._cursor.max())

    # ------------------------------------------------------------------ one controller tick
    def _one_thread(self, what: str) -> threading.RLock:
        """The simulator's lock, taken for `what` by this thread; ConcurrentUseError at once when
        another thread holds it. A tick's helper threads wait for the thread that started it,
        so a second thread ticking the same simulator would wait on them forever or corrupt the
        worlds: it gets an error instead, never a hang."""
        lock = self.__dict__["_in_use"]
        if not lock.acquire(blocking=False):
            self._busy(what)
        return lock

    @staticmethod
    def _busy(what: str) -> None:
        raise ConcurrentUseError(
            f"Simulator.{what}: another thread is inside this simulator. A simulator, and the env "
            f"that holds it, serves one thread at a time: make one env (or simulator) per thread")

    def tick(self, residual: np.ndarray | None = None, override: np.ndarray | None = None) -> Mapping[str, np.ndarray]:
        """Advance every active world by one controller period; returns the tick's log row.

        One thread at a time: a second thread's call meanwhile raises ConcurrentUseError (`_one_thread`).

        residual: (W, V, 3) m/s^2 added to the LQR command (e.g. an RL compensation action).
        override: (W, V, 3) m/s^2 replacing the LQR acceleration where finite (NaN keeps LQR).
        The row (name -> (W, ...) array: `sim.logs.ARRAY_SPECS` and the components' `OPTIONAL_SPECS`):
        the state at the tick's start and the command applied during it, fresh arrays never written
        again. A dict on the readable path, a `Row` on the fused one.
        """
        if residual is not None:
            residual = as_batch(residual, (self.W, self.V, 3))
        if override is not None:
            override = as_batch(override, (self.W, self.V, 3))
        lock = self.__dict__["_in_use"]  # (`_one_thread`, inline: once per tick)
        if not lock.acquire(blocking=False):
            self._busy("tick")
        try:
            plan = self._plan
            if not self._bound or plan is not None and plan.revision != self.physics.revision:
                self._bind()  # a component replaced, or set_body_mass changed the worlds
                plan = self._plan
            with profiling_timer_off():  # (MuJoCo's profiling timer: see sim.physics)
                row = self._tick_fused(plan, residual, override) if plan is not None \
                    else self._tick_readable(residual, override)
            if self._observe is not None:  # (after each tick, sim.predictor; None where the plan's kernel runs it)
                self._observe(row["t"], row["vel_est"], row["u_cmd"])
            self.__dict__["row"] = row  # (not a bound input: skips __setattr__, once per tick)
            mark_compiled()
        finally:
            lock.release()
        return row

    def _check(self, diverged: np.ndarray) -> None:
        """Count the tick for active worlds; end those that diverged or collided (they keep their rows)."""
        cfg = self.cfg
        status = self._status_new
        n_ended = status_kernel(
            self.physics.qpos, self._layout, self.physics.qvel, diverged, self.active, self.tick_index,
            cfg.max_distance, cfg.ground_clearance, self.vehicle_params.collision_xy, self.vehicle_params.collision_z,
            status,
        )
        if n_ended:
            self._end_worlds(status)

    def _end_worlds(self, status: np.ndarray) -> None:
        for w in np.flatnonzero(status):
            self.status[w] = status[w]
            what = Status(int(status[w])).description
            self.message[w] = f"world {w} (seed {self.seeds[w]}): {what} at t = {self.t[w]:.2f} s"
            self.active[w] = False
