"""A guard on learned compensation: use the model where it knows, fall back to no model where it does not.

`GuardedPredictor` wraps a learned predictor (`downwash.predictor.LearnedPredictor`) in the
predictor slot and scales each vehicle's prediction (its lateral and vertical parts) by
confidences in [0, 1]:

- **Support.** Every (neighbour, target) pair that acts on a vehicle (the predictor's
  neighbour set, targets below their neighbour) is described by the generalised invariants
  (`downwash.features`, feature set ``GUARD_FEATURES``: lateral offset, depth, both
  vehicles' speeds along and across the neighbour's axis, their angles) and both vehicles'
  kinds (the scene's, told by ``for_vehicles``; paper quads until then). A model's training
  data gives each feature's support, the range between its 0.1 % and 99.9 % quantiles
  (`downwash.support`, recorded in every checkpoint's data summary). A pair inside the support has
  confidence 1; each feature outside it costs linearly, down to 0 a quarter of the
  support's width beyond it (`Support.margin`); a pair's confidence is the product over its
  features, and a vehicle's the lowest of its pairs'.
- **Evidence outside the support.** Away from its data a model may still carry (a pair model
  among slowly moving neighbours, an indoor model whose wake the wind has weakened), and the
  forces the vehicle feels can show it. Outside the support of the continuous features the
  monitor's ``evidence``, ``sum f . r / (sum |r|^2 + skeptic)`` clipped to [0, 1], stands in
  for the support's confidence: the model flies in shadow (nothing applied, its prediction
  still compared with the forces felt) until the forces agree with it, then earns authority up
  to the least-squares scale. A right model predicting 1 m/s^2 earns 0.9 within a second
  (``skeptic`` 5 (m/s^2)^2); one that predicts the wrong force earns nothing. A vehicle kind the
  data never held is a hard veto whatever the evidence: a kind is not a continuous quantity to
  reach out along, and in a stack the forces felt in shadow are not those felt once the model
  acts (the summed paper-quad model in the stack of Crazyflies crashed when evidence could
  override the kinds).
- **Monitor.** Inside its support a model can still be wrong (a kind of vehicle its data held,
  flown in a new formation). After every tick the guard sees what the lab sees: the force each
  vehicle felt, ``f = a - u`` (the estimated velocity's change over the tick, less the command
  applied, compensation included: the label the model learned from, `downwash.labels`, here
  causal and unsmoothed). Its ``gain`` is the least-squares scale of the model's prediction
  ``r`` against those forces over the last ``monitor`` seconds (exponential weights),
  ``(sum f . r + prior) / (sum |r|^2 + prior)`` clipped to [0, 1]: 1 for a model that is right,
  1/3 for one that predicts three times the force, 0 for one that points the wrong way. The
  motion-capture noise in ``f`` has zero mean and is independent of ``r``, so it leaves the
  sums' expectations alone; ``prior`` (in (m/s^2)^2) is the evidence that a model is right
  before any is seen, which the first second outweighs. Any scale in [0, 1] at most the
  least-squares one leaves the error no larger than no model's (``|f - k r|^2 <= |f|^2`` for
  ``0 <= k <= 2 f.r / |r|^2``), which is this guard's promise in expectation.
  The monitor judges the prediction's lateral (x, y) and vertical (z) parts apart, with a gain
  each (the promise holds for each part, and so for their sum): a model can be right about
  the push down and wrong about the push sideways. Among a formation's moving neighbours the
  pair-trained deep set's lateral predictions carry nothing (their least-squares scale about
  0) while it under-predicts the vertical push (about 4); one gain over both applied the lateral
  noise in full. The parts are those of the world's vertical axis, about which the models are
  equivariant, so the guard is too. The evidence stays one sum over both parts: per part the
  smaller lateral forces rarely outweigh the skepticism, and models outside their support lost
  lateral help they had earned.
- **Fast monitor.** A second pair of sums with a short memory (``fast_monitor``, 0.2 s) gives a
  second scale per part, and each gain is the lower of the two: a model that was right for
  seconds and then over-predicts (a neighbour passing close) is turned down within a fifth of a
  second, where the one-second sums still hold the earlier agreement. Its prior (``fast_prior``,
  in (m/s^2)^2) damps the noise of its ten or so ticks: through 1 m/s^2 of it per axis a right
  model's median gain stays above 0.9, though single ticks dip lower.
- **Rate limit.** Each part's applied fraction may drop at once but rises by at most
  ``recovery`` per second (a model that left its support gets authority back over
  1 / recovery seconds, not in one tick).
- **Hard bound.** The applied prediction's magnitude is at most ``bound`` m/s^2.

Each part's applied fraction is the lowest of the kinds' confidence, the larger of the support's
confidence and the evidence, the monitor's gain of that part and the rate limit. The applied
prediction is each part times its fraction (then bounded), so the guard never increases a
prediction's magnitude,
passes in-support inputs through unchanged once the fraction has recovered (while the forces
felt agree: their noise costs a right model a percent or two of its gain in flight), and applies
nothing far outside the support until the forces felt there agree with the model, and nothing
at all to a vehicle kind its data never held (property tests).
Why a support check rather than an ensemble's disagreement: it needs no extra training,
serves every model kind and checkpoint as it is, is exact and cheap at 45 Hz, and an
ensemble trained on indoor data can agree confidently on a regime it never saw (a moving
leader): the support names that regime by its leader speed.

The guard keeps state (per world and vehicle the applied fractions, the gains, the evidence, the
model's last prediction, and the monitor's sums), so it is a stateful predictor (`sim.predictor.is_stateful`):
the simulator resets it with its worlds, tells it which are due, and calls ``observe`` after
every tick. ``applied`` holds the fraction of the prediction applied (|applied| / |prediction|)
at each world's last due call, which the
simulator logs per tick and vehicle. A call runs the compiled pass
(`downwash.guard_fused`), tested bit for bit against its NumPy reference (``reference``,
``confidence``); around a model with a compiled form and no state, the simulator's fused
tick runs the same pass after the model, and its monitor at the end of the tick (``compiled_guard``).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from downwash_core import libm
from downwash_core.errors import ConfigError
from downwash_core.geometry import dot
from downwash_core.params import RATES
from downwash_core.state import VehicleStates
from downwash.features import KIND_FEATURES, kind_descriptors, neighbour_kinds
from downwash.guard_fused import (CMD, DEN, EVIDENCE, FAST_DEN, FAST_NUM, FRACTION, GAIN, GUARD_FN, HELD, MONITOR_FN,
                                  MONITOR_WIDTH, NEXT, NUM, RAW, VEL, guard_into, monitor_into, pack_guard)
from downwash.predictor import clamp_magnitude
from downwash.support import (DEPTH_COLUMN, GUARD_FEATURES, MARGIN, SUPPORT_QUANTILE, Support, support_inputs,
                              support_of)
from sim.neighbours import gather_neighbours, select_neighbours
from sim.predictor import GUARD_STATE_WIDTH, CompiledGuard, CompiledPredictor, is_stateful

__all__ = ["GUARD_FEATURES", "SUPPORT_QUANTILE", "Support", "support_of", "GuardedPredictor", "GUARD_DEFAULTS",
           "guard_settings"]

# 1/s (0 to full in 0.2 s); m/s^2, the pair clamp's bound; s, the monitor's memory; (m/s^2)^2, its prior
# and the skepticism of its evidence outside the support; s and (m/s^2)^2, the fast sums' memory and prior
# (module doc)
MONITOR_PARTS = ("lateral", "vertical")  # the parts of a prediction the monitor judges apart (module doc)
GUARD_DEFAULTS = {"recovery": 5.0, "bound": 6.0, "monitor": 1.0, "prior": 1.0, "skeptic": 5.0, "fast_monitor": 0.2,
                  "fast_prior": 3.0}


def _by_part(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(..., 2): the dot products of a and b (..., 3) over their lateral (x, y) and vertical (z) parts."""
    return np.stack([a[..., 0] * b[..., 0] + a[..., 1] * b[..., 1], a[..., 2] * b[..., 2]], axis=-1)


def _lowest(x: np.ndarray, acting: np.ndarray, of: Any) -> np.ndarray:
    """(W, V): each vehicle's lowest `of` (a `Support` confidence) over the pairs x (W, V, K, features)
    acting on it (acting (W, V, K)); 1 with none."""
    return np.where(acting, of(x), 1.0).min(axis=-1, initial=1.0)


def guard_settings() -> dict[str, Any]:
    """The guard's settings as the experiments record them beside a guarded condition's results."""
    return {"features": GUARD_FEATURES, "kinds": list(KIND_FEATURES), "support_quantile": SUPPORT_QUANTILE,
            "margin": MARGIN, "monitor_parts": list(MONITOR_PARTS), **GUARD_DEFAULTS}


class GuardedPredictor:
    """A learned predictor behind the guard (module doc): (W, V, 3) m/s^2, never more than it predicts.

    predictor: a `downwash.predictor.LearnedPredictor` (its neighbour set chooses the pairs);
    support: a `Support`, by default the one its checkpoint's training data recorded;
    recovery: 1/s, how fast the applied fraction may rise; bound: m/s^2, the hard bound;
    monitor: s, the time constant of the monitor's sums; prior: (m/s^2)^2, its prior evidence that
    the model is right; skeptic: (m/s^2)^2, the evidence a model outside its support must first
    outweigh (module doc; inf: the support alone decides there); fast_monitor: s, the memory of the
    fast sums, and fast_prior: (m/s^2)^2, their prior (module doc);
    vehicle_kinds: the scene's V vehicle kinds (names or `VehicleKind`s; None: paper quads), as
    ``for_vehicles`` tells them.
    """

    stateful = True

    def __init__(self, predictor: Any, support: Support | None = None, recovery: float = GUARD_DEFAULTS["recovery"],
                 bound: float = GUARD_DEFAULTS["bound"], predictor_hz: float = RATES.predictor_hz,
                 vehicle_kinds: Any = None, monitor: float = GUARD_DEFAULTS["monitor"],
                 prior: float = GUARD_DEFAULTS["prior"], skeptic: float = GUARD_DEFAULTS["skeptic"],
                 fast_monitor: float = GUARD_DEFAULTS["fast_monitor"],
                 fast_prior: float = GUARD_DEFAULTS["fast_prior"]):
        if support is None:
            record = ((getattr(predictor, "record", None) or {}).get("data") or {}).get("support")
            if record is None:
                raise ConfigError("guard: the model's checkpoint records no support of its training data (made by "
                                  "older code); retrain it, or pass support=downwash.guard.support_of(...)")
            support = Support.from_record(record)
        for name, value in (("recovery", recovery), ("bound", bound), ("predictor_hz", predictor_hz),
                            ("monitor", monitor), ("prior", prior), ("skeptic", skeptic),
                            ("fast_monitor", fast_monitor), ("fast_prior", fast_prior)):
            if not (isinstance(value, (int, float)) and (math.isfinite(value) or name == "skeptic" and value == math.inf)
                    and value > 0):
                what = "a number > 0 (inf: no authority outside the support)" if name == "skeptic" else "a finite number > 0"
                raise ConfigError(f"{name}: expected {what}, got {value!r}")
        self.predictor, self.support, self.predictor_hz = predictor, support, float(predictor_hz)
        self.recovery, self.bound = float(recovery), float(bound)
        self.monitor, self.prior, self.skeptic = float(monitor), float(prior), float(skeptic)
        self.fast_monitor, self.fast_prior = float(fast_monitor), float(fast_prior)
        self.vehicle_kinds = None if vehicle_kinds is None else tuple(getattr(k, "name", k) for k in vehicle_kinds)
        self._kinds = None if vehicle_kinds is None else kind_descriptors(vehicle_kinds)  # (V, D)
        self.step = self.recovery / self.predictor_hz  # the most the fraction rises per call
        self.applied: np.ndarray | None = None  # (W, V) the fraction applied at each world's last due call
        self._state: np.ndarray | None = None  # (W, V, GUARD_STATE_WIDTH) per world, carried between calls
        self._seen: np.ndarray | None = None  # (W, V, MONITOR_WIDTH) the monitor's sums and last ticks (`observe`)
        self._seen_t: np.ndarray | None = None  # (W,) the time of each world's last tick seen (NaN: none)
        self._pack = pack_guard(self.support, predictor.neighbours, self.step, self.bound, self._kinds)
        self._monitor_pack = (np.array([self.monitor, self.prior, self.skeptic, self.fast_monitor, self.fast_prior]),
                              np.array([MONITOR_WIDTH], np.int64))

    def for_vehicles(self, kinds: Any) -> "GuardedPredictor":
        """This guard for a scene of these vehicle kinds: its support check reads them, and its
        predictor is told them (`LearnedPredictor.for_vehicles`)."""
        inner = self.predictor.for_vehicles(kinds)
        told = kind_descriptors(kinds)
        mine = np.zeros_like(told) if self._kinds is None else self._kinds  # (None: paper quads)
        if inner is self.predictor and mine.shape == told.shape and np.array_equal(mine, told):
            return self  # (the guard a scene of paper quads flies is the one it was given)
        return GuardedPredictor(inner, self.support, predictor_hz=self.predictor_hz, vehicle_kinds=kinds,
                                **self._settings())

    def reset(self, worlds: Any = None) -> None:
        """These worlds (None: all) start afresh: no compensation, rising at the recovery rate, and
        a monitor that has seen nothing (gains 1)."""
        if self._state is not None:
            self._start(slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64))
        if is_stateful(self.predictor):
            self.predictor.reset(worlds)

    def _start(self, rows: Any) -> None:
        """These rows of the guard's arrays as a fresh world's: nothing applied, gains 1, no evidence, no tick seen."""
        self._state[rows] = 0.0
        self._state[rows, :, GAIN:GAIN + 2] = 1.0
        self._seen[rows] = 0.0
        self._seen_t[rows] = np.nan  # (no tick seen: the next one starts the sums)

    def observe(self, t: np.ndarray, vel_est: np.ndarray, u_cmd: np.ndarray) -> None:
        """The monitor (module doc), after each tick, from the tick's row: t (W,) s, the estimated
        velocities vel_est (W, V, 3) m/s at its start, and the commands u_cmd (W, V, 3) m/s^2
        applied during it. The force of the tick before, (vel_est - its vel_est) / (t - its t) - its
        u_cmd, is paired with the prediction the model made before that tick (the one held through
        it), and the gains and the evidence set from the decayed sums. A world whose last tick is unseen (reset,
        ended, or not finite) adds nothing. Runs the compiled pass (`downwash.guard_fused.monitor_into`),
        tied to ``monitor_reference``."""
        state = self._state
        if state is None or len(state) != len(t):
            return  # (no call yet in these worlds: nothing predicted to judge)
        monitor_into(t, vel_est, u_cmd, state, self._seen, self._seen_t, self.monitor, self.prior,
                     self.skeptic, self.fast_monitor, self.fast_prior)  # (float64 arrays)

    def monitor_reference(self, t: np.ndarray, vel_est: np.ndarray, u_cmd: np.ndarray, state: np.ndarray,
                          seen: np.ndarray, seen_t: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``observe`` in NumPy, the readable reference of its compiled pass: (the next state, seen
        (W, V, `MONITOR_WIDTH`), seen_t (W,)) after the tick, from the guard's arrays before it."""
        dt = t - seen_t
        force = (vel_est - seen[..., VEL:VEL + 3]) / np.where(dt > 0, dt, 1.0)[:, None, None] - seen[..., CMD:CMD + 3]
        raw = seen[..., HELD:HELD + 3]
        ok = (dt > 0)[:, None] & np.isfinite(force.sum(-1) + raw.sum(-1))
        after, state = seen.copy(), state.copy()
        for sums, to, memory in ((NUM, DEN, self.monitor), (FAST_NUM, FAST_DEN, self.fast_monitor)):
            decay = libm.exp(-np.where(ok, dt[:, None], 0.0) / memory)[..., None]
            num, den = seen[..., sums:sums + 2], seen[..., to:to + 2]
            after[..., sums:sums + 2] = np.where(ok[..., None], decay * num + _by_part(force, raw), num)
            after[..., to:to + 2] = np.where(ok[..., None], decay * den + _by_part(raw, raw), den)
        scale = [np.clip((after[..., sums:sums + 2] + prior) / (after[..., to:to + 2] + prior), 0.0, 1.0)
                 for sums, to, prior in ((NUM, DEN, self.prior), (FAST_NUM, FAST_DEN, self.fast_prior))]
        state[..., GAIN:GAIN + 2] = np.minimum(*scale)
        num, den = after[..., NUM:NUM + 2], after[..., DEN:DEN + 2]
        state[..., EVIDENCE] = np.clip((num[..., 0] + num[..., 1]) / (den[..., 0] + den[..., 1] + self.skeptic), 0.0, 1.0)
        after[..., HELD:HELD + 3], after[..., NEXT:NEXT + 3] = seen[..., NEXT:NEXT + 3], state[..., RAW:RAW + 3]
        after[..., VEL:VEL + 3], after[..., CMD:CMD + 3] = vel_est, u_cmd
        return state, after, np.array(t, dtype=np.float64)

    def confidence(self, estimated: VehicleStates) -> np.ndarray:
        """(W, V) in [0, 1]: each vehicle's lowest confidence over the pairs acting on it (1 with none)."""
        return _lowest(*self._pairs(estimated), self.support.confidence)

    def kind_confidence(self, estimated: VehicleStates) -> np.ndarray:
        """(W, V) in [0, 1]: ``confidence`` over the vehicle kinds alone (`Support.kind_confidence`)."""
        return _lowest(*self._pairs(estimated), self.support.kind_confidence)

    def _pairs(self, estimated: VehicleStates) -> tuple[np.ndarray, np.ndarray]:
        """Every (vehicle, neighbour) pair as the support describes it (W, V, K, features), and whether
        it acts (the vehicle below its neighbour) (W, V, K)."""
        pos, vel, rot = estimated.pos, estimated.vel, estimated.rot
        index, mask = select_neighbours(pos, self.predictor.neighbours)
        g = gather_neighbours(pos, vel, rot, index, mask)
        self._check_kinds(pos.shape[1])
        kind_a = kind_b = None
        if self._kinds is not None:
            kind_a, kind_b = neighbour_kinds(self._kinds, index, mask), self._kinds[:, None, :]
        x = support_inputs(g["dp"], g["v_a"], np.broadcast_to(g["v_b"][..., None, :], g["dp"].shape), g["R_a"],
                           kind_a, kind_b)
        return x, mask & (x[..., DEPTH_COLUMN] > 0)

    def __call__(self, estimated: VehicleStates, true: VehicleStates | None = None,
                 due: np.ndarray | None = None) -> np.ndarray:
        when = {"due": due} if is_stateful(self.predictor) else {}
        out = np.array(self.predictor(estimated, true, **when), dtype=np.float64, order="C")  # scaled in place
        W, V = out.shape[:2]
        self._check_kinds(V)
        state, applied = self._arrays(W, V)
        due = np.ones(W, np.uint8) if due is None else np.ascontiguousarray(due, dtype=bool).view(np.uint8)
        pos, vel, rot = (np.ascontiguousarray(a, dtype=np.float64)
                         for a in (estimated.pos, estimated.vel, estimated.rot))
        guard_into(pos, vel, rot, due, out, state, applied, *self._pack)
        return out

    def reference(self, estimated: VehicleStates, raw: np.ndarray, state: np.ndarray,
                  due: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One call in NumPy, the readable reference of the compiled pass (`downwash.guard_fused`) that
        ``__call__`` runs: (the applied prediction, the next state, the fraction applied, |applied| /
        |prediction| (due worlds')), for the model's prediction raw (W, V, 3), the state (W, V, GUARD_STATE_WIDTH) and
        due (W,) bool."""
        x, acting = self._pairs(estimated)
        support, kinds = (_lowest(x, acting, of) for of in (self.support.confidence, self.support.kind_confidence))
        conf = np.minimum(kinds, np.maximum(support, state[..., EVIDENCE]))[..., None]
        frac = np.minimum(np.minimum(conf, state[..., GAIN:GAIN + 2]), state[..., FRACTION:FRACTION + 2] + self.step)
        out = clamp_magnitude(raw * frac[..., [0, 0, 1]], self.bound)  # (lateral, lateral, vertical)
        raw_norm = np.sqrt(dot(raw, raw))
        applied = np.where(raw_norm > 0, np.sqrt(dot(out, out)) / np.maximum(raw_norm, 1e-300), 1.0)
        after = state.copy()
        after[due, :, FRACTION:FRACTION + 2], after[due, :, RAW:RAW + 3] = frac[due], raw[due]
        return out, after, applied

    def compiled_guard(self, W: int, V: int) -> tuple[CompiledPredictor, CompiledGuard] | None:
        """The fused loop's form (`sim.predictor`): the model's compiled predictor and this guard's
        pass over its (W, V) state, with its monitor (``observe``) compiled; None when the model has
        no compiled form or keeps state."""
        inner = None if is_stateful(self.predictor) else getattr(self.predictor, "compiled", lambda: None)()
        if inner is None or (self._kinds is not None and len(self._kinds) != V):
            return None
        state, applied = self._arrays(W, V)
        return inner, CompiledGuard(GUARD_FN.address, *self._pack, state, applied, MONITOR_FN.address,
                                    *self._monitor_pack, self._seen, self._seen_t)

    def _arrays(self, W: int, V: int) -> tuple[np.ndarray, np.ndarray]:
        """The state (W, V, GUARD_STATE_WIDTH) and applied (W, V) arrays the calls advance in place
        (fresh for another shape, reset: nothing applied yet, a monitor that has seen nothing)."""
        if self._state is None or self._state.shape[:2] != (W, V):
            self._state, self._seen, self._seen_t = (np.empty((W, V, GUARD_STATE_WIDTH)),
                                                     np.empty((W, V, MONITOR_WIDTH)), np.empty(W))
            self.applied = np.zeros((W, V))  # (nothing applied before a world's first due call)
            self._start(slice(None))
        return self._state, self.applied

    def _check_kinds(self, V: int) -> None:
        if self._kinds is not None and len(self._kinds) != V:
            raise ConfigError(f"guard: told {len(self._kinds)} vehicle kinds, flies {V} vehicles")

    def _settings(self) -> dict[str, float]:
        """This guard's value of each of `GUARD_DEFAULTS`' settings, in their order."""
        return {name: getattr(self, name) for name in GUARD_DEFAULTS}

    def describe(self) -> dict[str, Any]:
        inner = getattr(self.predictor, "describe", lambda: {})()
        return {**inner, "guard": {"support": self.support.describe(), **self._settings()}}
