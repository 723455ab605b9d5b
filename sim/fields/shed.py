"""A ground-truth wake with memory: the momentum jet, shed by the rotors and carried down.

`sim.fields.momentum.MomentumWake` is a steady jet hung below the leader at this instant.
A real wake is shed by the rotors and carried away by its own induced velocity and by
the wind, so a follower meets air that the leader pushed down a moment earlier,
somewhere else (below ~2.5 vehicle diameters the combined wake is a turbulent jet:
Bauersfeld, Muller, Ziegler, Coletti & Scaramuzza, *Robotics meets Fluid Dynamics: A
Characterization of the Induced Airflow below a Quadrotor as a Turbulent Jet*, RA-L 2024).
`ShedWake` keeps that memory as explicit, batched state: W worlds x V vehicles x N
elements, a ring buffer per vehicle (N = ceil(rate_hz max_age)).

1. Shedding. Every 1 / rate_hz (a clock per world; dt may be shorter or longer) each
   vehicle i sheds an element at its rotor plane (its centre p_i): axis d = -n_i
   (n_i = R_i[:, 2], its thrust axis at that instant), thrust T_i (N; default the law's
   estimate `MomentumWake.leader_thrust`, thrust_scale m g / clip(n_z, 0.5, 1)),
   travelled depth s = 0. An element shed tau before the end of a step (a step longer
   than the period sheds several) starts at p_i - v_i tau and is advanced by tau.
2. Convection. An element moves along its own axis at a fraction kappa (`convection`) of
   the steady jet's centreline speed at its own travelled depth and thrust, plus the wind
   w (m/s, uniform per world):
       ds/dt = kappa U_c(s, T),   dx/dt = kappa U_c(s, T) d + w.
   `MomentumWake.centreline` (the contraction joined to the far-field round jet) scales
   with the induced velocity, U_c(s, T) = v_h(T) phi(s), v_h = sqrt(T / (2 rho A)), so an
   element of constant thrust is integrated exactly, whatever dt:
       s(age) = G^-1(kappa v_h(T) age),   G(s) = int_0^s ds' / phi(s'),
   G tabulated once per vehicle kind from the law's centreline (10^4 depths, geometric
   from 10 um to 10 km; s within 1e-6 of quadrature). Elements older than max_age are
   dropped. Under a hovering paper quad in still air an element reaches depth s after
   t(s) = int_0^s ds' / (kappa U_c(s')): with kappa = 0.5, 0.057 / 0.10 / 0.18 / 0.62 s
   at 0.6 / 1 / 1.5 / 3 m, so the default max_age = 0.8 s reaches 3.4 m (N = 80).
   Why kappa = 0.5: an element stands for a slab of the jet, and what is carried is the
   bulk of its cross-section, not the centreline. For the round-jet profile
   U = U_c (1 + a xi^2)^-2 (Pope, *Turbulent Flows*, 2000, sec. 5.2) the area-mean axial
   speed inside radius xi is U_c / (1 + a xi^2): exactly U_c / 2 at xi = 1/sqrt(a) = 1.55
   half-widths, where (in the far field) the radial flow turns from spreading to
   entrainment, the jet's edge; 0.71 U_c inside one half-width. The front of a starting turbulent jet likewise
   advances at about half the centreline speed of the steady jet behind it (Witze, AIAA
   J. 18, 1980; Sangras, Kwon & Faeth, J. Heat Transfer 124, 2002).
3. The wake's air velocity. A vehicle's valid elements, in shedding order, are the
   vertices of a polyline (its convected centreline) that starts at the vehicle's rotor
   plane (vertex 0: its position now, s = 0, axis -n now, the newest element's thrust).
   At a point p, the nearest point c on it (segment projection) gives by linear
   interpolation along that segment the travelled depth s, thrust T and axis d (renormalised);
   r = |p - c|, and the momentum jet's profile there (the law's `induced_velocity`: U(s, r) and
   V(s, r) / r with its fade across the rotor plane) gives
       u = U d + (V / r) r_perp,   r_perp = (p - c) minus its part along the segment.
   Beyond the oldest element the wake ends: the speed falls off with the distance from
   its last element as across the jet (over about one half-width). Points above the
   shedding vehicle's rotor plane, ((p - p_i) . n_i > 0), get exactly 0, as in the law.
   A hovering leader in still air has a straight wake with s equal to the depth, and
   reproduces `MomentumWake` there to rounding.
4. On each vehicle (`forces`, (W, V_source, V_target, 3)): the law's follower action
   (`MomentumWake.follower_response`), fed the shed wake's air velocity: the target's
   rotors on a ring of `ring_points` azimuths (k + 1/2) 2 pi / K from its body x axis, at
   `follower_arm` in its rotor plane, each losing thrust as a rotor climbing at the air's
   speed down through it along the target's own axis n_b; its airframe's drag on the air
   velocity at its centre. Ring points are taken at the centre's depth and measured from
   the centreline's local segment (the law evaluates its ring at the centre's depth too).
   Each term minus its value in still air; a vehicle's own wake does not act on it (the
   diagonal is 0). The aggregation over sources is linear, forces.sum(axis=1).
5. Vehicle kinds (`for_vehicles`): each vehicle's elements carry its own kind's jet (its
   mass and disc area set v_h, its rotor radius the fade) and each target responds with its
   own rotors, arm and airframe: per ordered pair the law with
   `downwash_core.vehicles.momentum_wake_kwargs(source, target)` and the drag area scaled by
   `momentum_drag_area_scale`, the rule of `sim.vehicle_params.pair_field` (two paper quads:
   the law as given).

Assumptions and limits: the elements do not interact (no vortex-ring dynamics at a thrust
step, no merging of several vehicles' wakes: forces add); each element keeps the speed of a
steady straight jet of its thrust at its depth, so a bent wake has the profile of a straight
one about its local centreline; a wind carries the wake kinematically (no crossflow
deflection of the jet's momentum, the wake's share excludes the ambient wind: `forces`
takes the wind only to know each target's speed relative to the air); no ground effect;
beyond max_age (default 0.8 s: 3.4 m below a hovering paper quad) the wake is gone.
Units: m, m/s, s, N; forces (W, V, V, 3) m/s^2, world frame, z up. Cost: O(W V N) per
`step`, O(W V^2 N) per `forces`. Both are compiled (`sim.fields.shed_kernels`, numba, the
laws and tables handed over as arrays), beside their NumPy reference (`compiled=False`:
`_step_reference`, `_forces_reference`, whose arithmetic they repeat in order, so that the two
agree to the bit on an AVX2 CPU). The elements' state and the search along the centreline (3)
are `sim.fields.shed_centreline`'s. Median per call on a 2-core AMD EPYC, step + forces: one world
8.5 + 8 us for 2 vehicles, 12 + 22 us for 5 (NumPy: 0.15 + 0.6 ms, 0.15 + 0.63 ms); 64 worlds
0.19 + 0.15 ms for 2, 0.47 + 1.3 ms for 5 (NumPy: 0.5 + 1.1, 1.1 + 3.9 ms). What is left of
`forces` is the law's transcendental functions (12 pow per pair, 3 or 4 per rotor of the ring).
A one-world 2-vehicle flight in the simulator (readable path): 0.24 ms per control tick (1.1 ms
with `make_field('momentum')`, whose law is NumPy; 2.5 ms with this wake's NumPy reference).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import Any, NamedTuple

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.geometry import dot as _dot
from downwash_core.params import GRAVITY
from downwash_core.validate import count, number
from downwash_core.vehicles import get_vehicle
import sim.fields.momentum as _momentum
import sim.fields.shed_kernels as _kernels
from sim.fields.kinds import pair_field
from sim.fields.momentum import MomentumWake
from sim.fields.shed_centreline import TINY as _TINY
from sim.fields.shed_centreline import Local as _Local
from sim.fields.shed_centreline import WakeState, nearest
from sim.fields.shed_centreline import air as _air

__all__ = ["ShedWake", "WakeState"]

_MAX_ELEMENTS = 100_000  # -, per vehicle: a cap on the ring buffer's memory
_ROUND = 1e-9  # -, relative slack on the shedding clock and the age limit (accumulated rounding)
_TABLE_S = (1e-5, 1e4)  # m, the travel table's depths (geometric), beyond any wake's max_age
_TABLE_POINTS = 10_000  # -, spacing ratio 1.002: s(age) within 1e-6 (relative) of quadrature
_ESTIMATE = np.zeros((0, 0))  # the compiled step's "no thrust given" (each kind's estimate)
_STILL = np.zeros((0, 3))  # the compiled passes' "no wind"
_LEVEL = np.eye(3)  # a level leader's attitude: its thrust estimate is the hover thrust times thrust_scale


class _Source(NamedTuple):
    """A source kind's jet: its law and its travel table, s(age) of an element of thrust T (module docstring, 2)."""

    law: MomentumWake
    reduced: np.ndarray  # (M,) m, G(s) = int_0^s U_c(0, T) / U_c(s', T) ds' (the same for every T)
    s: np.ndarray  # (M,) m, the depths of the table
    vh_per_sqrt_thrust: float  # m/s/sqrt(N): v_h = U_c(0, T) = this sqrt(T)

    @classmethod
    def of(cls, law: MomentumWake) -> "_Source":
        s = np.concatenate([[0.0], np.geomspace(_TABLE_S[0], _TABLE_S[1], _TABLE_POINTS)])
        c = float(law.centreline(0.0, 1.0)[0])
        inv = c / law.centreline(s, 1.0)[0]  # v_h / U_c(s): 1 at the rotor plane, ~s far down
        reduced = np.concatenate([[0.0], np.cumsum(0.5 * (inv[1:] + inv[:-1]) * np.diff(s))])
        return cls(law, reduced, s, c)

    def depth(self, kappa: float, thrust: np.ndarray, age: np.ndarray) -> np.ndarray:
        """m, the travelled depth of elements of this thrust (N) and age (s): G^-1(kappa v_h(T) age)."""
        travelled = (kappa * self.vh_per_sqrt_thrust) * np.sqrt(np.maximum(thrust, 0.0)) * age
        return np.interp(travelled, self.reduced, self.s)


@dataclass(frozen=True)
class ShedWake:
    """A wake with memory: elements shed at `rate_hz`, convected at `convection` U_c plus the wind.

    See the module docstring for the model and sources. Constants are checked on
    construction (ConfigError naming the bad one); `vehicles` (kind names, one per vehicle)
    is empty for vehicles that are all of the law's kind (any V).
    """

    law: MomentumWake = MomentumWake()  # the jet (centreline, profile) and the follower's action
    rate_hz: float = 100.0  # Hz, elements shed per second per vehicle (the autopilot's rate)
    max_age: float = 0.8  # s, older elements are dropped (3.4 m below a hovering paper quad)
    convection: float = 0.5  # -, kappa: elements move at kappa U_c(s) along their axis
    vehicles: tuple[str, ...] = ()  # downwash_core.vehicles kinds, one per vehicle; () all the law's

    def __post_init__(self) -> None:
        if not isinstance(self.law, MomentumWake):
            raise ConfigError(f"law: expected a sim.fields.momentum.MomentumWake, got {type(self.law).__name__}")
        for name, unit, hi in (("rate_hz", "Hz", 1e4), ("max_age", "s", 60.0), ("convection", "-", 2.0)):
            object.__setattr__(self, name, number(name, getattr(self, name), unit, 0.0, hi, lo_open=True))
        n = math.ceil(self.rate_hz * self.max_age * (1.0 - _ROUND))
        if not 1 <= n <= _MAX_ELEMENTS:
            raise ConfigError(f"max_age: rate_hz * max_age = {n} elements per vehicle; allowed 1 to {_MAX_ELEMENTS}")
        if isinstance(self.vehicles, str):
            raise ConfigError(f"vehicles: expected a sequence of kind names, got {self.vehicles!r}")
        names = tuple(get_vehicle(k).name for k in self.vehicles)
        object.__setattr__(self, "vehicles", names)
        object.__setattr__(self, "_n", n)
        object.__setattr__(self, "_period", 1.0 / self.rate_hz)  # s
        # the laws: one per source kind (its jet), one per ordered pair of kinds (jet and follower)
        kinds = tuple(dict.fromkeys(names))
        if not kinds:
            sources, pairs = (_Source.of(self.law),), ((self.law, None),)
            kind_of = None
        else:
            kind_of = np.array([kinds.index(k) for k in names])
            sources = tuple(_Source.of(self._pair_law(k, k)) for k in kinds)  # the source's part is the same
            groups = []
            for i, a in enumerate(kinds):
                for j, b in enumerate(kinds):
                    groups.append((self._pair_law(a, b), (kind_of[:, None] == i) & (kind_of[None, :] == j)))
            pairs = tuple(groups)
        object.__setattr__(self, "_kind_of", kind_of)
        object.__setattr__(self, "_sources", sources)
        object.__setattr__(self, "_pairs", pairs)
        object.__setattr__(self, "_compiled", self._kernel_constants())

    def _kernel_constants(self) -> dict[str, np.ndarray]:
        """The laws and tables as the compiled passes read them (`sim.fields.shed_kernels`): plain arrays."""
        m = _momentum
        n_kinds = len(self._sources)
        pair = np.stack([_kernels.pair_constants(law, GRAVITY, m.PROFILE_A, m.BLEND, m.C_STAR, m.C_SMALL)
                         for law, _ in self._pairs]).reshape(n_kinds, n_kinds, _kernels.N_PAIR)
        source = np.zeros((n_kinds, _kernels.N_SOURCE))
        source[:, _kernels.S_TRAVEL] = [self.convection * src.vh_per_sqrt_thrust for src in self._sources]
        source[:, _kernels.S_THRUST] = [float(src.law.leader_thrust(_LEVEL)) for src in self._sources]
        x = np.stack([src.reduced for src in self._sources])
        s = np.stack([src.s for src in self._sources])
        K = self.law.ring_points
        azimuth = (np.arange(K) + 0.5) * (2.0 * math.pi / K)  # as `_forces_reference`
        emin = math.frexp(x[:, 1].min())[1] - 1  # the search guide's buckets: from below the smallest G > 0 ...
        n_buckets = (math.frexp(x[:, -1].max())[1] + 1 - emin) * _kernels.BUCKETS_PER_OCTAVE  # ... past the top
        return dict(pair=pair, source=source, table_x=x, table_s=s,
                    table_slope=(s[:, 1:] - s[:, :-1]) / (x[:, 1:] - x[:, :-1]),  # np.interp's slopes
                    table_start=np.stack([_kernels.bucket_starts(row, emin, n_buckets) for row in x]),
                    emin=emin,
                    ring_cos=np.cos(azimuth), ring_sin=np.sin(azimuth),
                    kind_of=None if self._kind_of is None else self._kind_of.astype(np.int64))

    def _kinds(self, V: int) -> np.ndarray:
        """(V,) each vehicle's row of the compiled passes' per-kind constants."""
        kind_of = self._compiled["kind_of"]
        return np.zeros(V, np.int64) if kind_of is None else kind_of

    def _pair_law(self, source: str, target: str) -> MomentumWake:
        """The law of an ordered pair of kinds: `sim.fields.kinds.pair_field`'s, the one rule of every field."""
        return pair_field(self.law, get_vehicle(source), get_vehicle(target))

    # ------------------------------------------------------------------ construction and provenance
    @property
    def n_elements(self) -> int:
        """N, the ring buffer's length per vehicle: ceil(rate_hz max_age)."""
        return self._n

    def for_vehicles(self, kinds: Any) -> "ShedWake":
        """This wake for V vehicles of these kinds (names or `downwash_core.vehicles.VehicleKind`s)."""
        return dataclasses.replace(self, vehicles=tuple(getattr(k, "name", k) for k in kinds))

    def describe(self) -> dict[str, Any]:
        """Stable provenance: name, type, every constant and the law's describe() (no addresses)."""
        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "name": "shed",
                "rate_hz": self.rate_hz, "max_age": self.max_age, "convection": self.convection,
                "vehicles": list(self.vehicles), "law": self.law.describe()}

    # ------------------------------------------------------------------ state
    def initial_state(self, n_worlds: int, n_vehicles: int) -> WakeState:
        """An empty wake for W worlds and V vehicles (no elements; the first is shed one period in)."""
        W = count("n_worlds", n_worlds, 1)
        V = count("n_vehicles", n_vehicles, 1)
        self._check_vehicles(V)
        N = self._n
        return WakeState(pos=np.zeros((W, V, N, 3)), axis=np.zeros((W, V, N, 3)), depth=np.zeros((W, V, N)),
                         thrust=np.zeros((W, V, N)), age=np.zeros((W, V, N)), valid=np.zeros((W, V, N), bool),
                         cursor=np.zeros(W, np.int64), clock=np.zeros(W))

    def reset(self, state: WakeState, worlds: Any = None) -> WakeState:
        """Empty the wake of some worlds in place (a (W,) bool mask or indices; all when None); returns `state`."""
        W, _, _ = self._check_state(state)
        w = np.arange(W) if worlds is None else np.asarray(worlds)
        if w.dtype == bool and w.shape != (W,):
            raise ConfigError(f"worlds: expected a (W,) = ({W},) mask or indices, got shape {w.shape}")
        state.valid[w] = False
        state.cursor[w] = 0
        state.clock[w] = 0.0
        return state

    def step(self, state: WakeState, dt: float, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray,
             thrust: Any = None, wind: Any = None, compiled: bool = True) -> WakeState:
        """Advance the wake by dt (s) in place, then shed; returns `state`.

        Args:
            state: from `initial_state`, (W, V, N).
            dt: s, > 0.
            pos: (W, V, 3) m, world frame: the vehicles' positions (rotor planes).
            vel: (W, V, 3) m/s, world frame: the vehicles' velocities.
            rot: (W, V, 3, 3) body-to-world attitudes; the thrust axis is rot[..., :, 2].
            thrust: optional (W, V) N; default `MomentumWake.leader_thrust(rot)` of each vehicle's kind.
            wind: optional (W, 3) m/s, world frame: the air's velocity, uniform over each world.
            compiled: the compiled pass (`sim.fields.shed_kernels.step`); False: the NumPy reference.
        """
        if not compiled:
            return self._step_reference(state, dt, pos, vel, rot, thrust, wind)
        W, V, _ = self._check_state(state)
        dt = number("dt", dt, "s", 0.0, 1e3, lo_open=True)
        args = dict(pos=_array("pos", pos, (W, V, 3), False), vel=_array("vel", vel, (W, V, 3), False),
                    rot=_array("rot", rot, (W, V, 3, 3), False),
                    thrust=_ESTIMATE if thrust is None else _array("thrust", thrust, (W, V), False),
                    wind=_STILL if wind is None else _array("wind", wind, (W, 3), False))
        c = self._compiled
        bad = _kernels.step(state.pos, state.axis, state.depth, state.thrust, state.age, state.valid, state.cursor,
                            state.clock, dt, *args.values(), self._kinds(V), c["source"], c["table_x"],
                            c["table_s"], c["table_slope"], c["table_start"], c["emin"], self._period, self.max_age,
                            _ROUND)
        if bad:
            raise ConfigError(f"{list(args)[bad - 1]}: must be finite")
        return state

    def _step_reference(self, state: WakeState, dt: float, pos: Any, vel: Any, rot: Any, thrust: Any = None,
                        wind: Any = None) -> WakeState:
        """The readable reference of `step` (NumPy), the same arguments."""
        W, V, N = self._check_state(state)
        dt = number("dt", dt, "s", 0.0, 1e3, lo_open=True)
        pos, vel = _array("pos", pos, (W, V, 3)), _array("vel", vel, (W, V, 3))
        rot = _array("rot", rot, (W, V, 3, 3))
        if thrust is None:
            thrust = self._per_source(lambda src, r: src.law.leader_thrust(r), rot)
        else:
            thrust = _array("thrust", thrust, (W, V))
        wind = np.zeros((W, 3)) if wind is None else _array("wind", wind, (W, 3))
        # carry every element (invalid ones too: their values are never read), then age them out
        state.age += dt
        self._carry(state.pos, state.axis, state.depth, state.thrust, state.age, dt, wind[:, None, None, :])
        state.valid &= state.age <= self.max_age * (1.0 + _ROUND)
        # shed: the clock crossed k periods; the i-th crossing happened clock - i period ago
        state.clock += dt
        k = np.floor(state.clock / self._period * (1.0 + _ROUND) + _ROUND).astype(np.int64)
        m = np.minimum(k, N)  # only the newest N crossings would survive in the ring
        n_axis = -rot[..., :, 2]
        for j in range(int(m.max())):  # oldest first: shedding order is ring order
            w = np.flatnonzero(j < m)
            i = k[w] - m[w] + 1 + j  # the crossing, counted from the last shedding
            tau = np.maximum(state.clock[w] - i * self._period, 0.0)[:, None]  # s, (n, 1)
            new_pos = pos[w] - vel[w] * tau[..., None]
            new_depth = np.zeros((w.size, V))
            new_axis = n_axis[w]
            self._carry(new_pos, new_axis, new_depth, thrust[w], tau, tau, wind[w][:, None, :])
            slot = state.cursor[w]
            state.pos[w, :, slot] = new_pos
            state.axis[w, :, slot] = new_axis
            state.depth[w, :, slot] = new_depth
            state.thrust[w, :, slot] = thrust[w]
            state.age[w, :, slot] = tau
            state.valid[w, :, slot] = tau <= self.max_age * (1.0 + _ROUND)
            state.cursor[w] = (slot + 1) % N
        state.clock -= k * self._period
        np.maximum(state.clock, 0.0, out=state.clock)
        return state

    def _carry(self, pos, axis, depth, thrust, age, dt, wind) -> None:
        """Carry elements in place to their new age (s) over the last dt (s; scalars or arrays broadcasting
        to depth's shape): depth = s(age, thrust) exactly, pos moves by the change along its axis plus wind dt.

        pos, axis (..., 3) m, -; depth, thrust (...) m, N; wind broadcasting to pos, m/s."""
        age = np.broadcast_to(age, depth.shape)
        new = self._per_source(lambda src, T, a: src.depth(self.convection, T, a), thrust, age)
        pos += (new - depth)[..., None] * axis + wind * np.asarray(dt)[..., None]
        depth[...] = new

    # ------------------------------------------------------------------ the wake's air
    def air_velocity(self, state: WakeState, pos: np.ndarray, rot: np.ndarray, points: np.ndarray) -> np.ndarray:
        """(W, V, P, 3) m/s, world frame: the air velocity of each vehicle's wake (axis 1) at points (W, P, 3) m.

        pos (W, V, 3) m and rot (W, V, 3, 3): the vehicles now (their rotor planes start the wakes).
        """
        W, V, _ = self._check_state(state)
        pos, rot = _array("pos", pos, (W, V, 3)), _array("rot", rot, (W, V, 3, 3))
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 3 or points.shape[0] != W or points.shape[2] != 3:
            raise ConfigError(f"points: expected (W, P, 3) = ({W}, P, 3) but found {points.shape}")
        loc = nearest(state, pos, rot, points)
        r2 = _dot(loc.offset, loc.offset)
        axial, radial = self._per_source(lambda src, s, r2, T: src.law.induced_velocity(s, r2, T), loc.s, r2, loc.thrust)
        return _air(axial, radial, loc, loc.offset)

    # ------------------------------------------------------------------ the force
    def forces(self, state: WakeState, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray,
               wind: Any = None, compiled: bool = True) -> np.ndarray:
        """(W, V, V, 3) m/s^2, world frame: the force of each vehicle's wake (axis 1) on each vehicle (axis 2).

        Args:
            state: the wake (W, V, N) after `step`.
            pos: (W, V, 3) m, world frame.
            vel: (W, V, 3) m/s, world frame.
            rot: (W, V, 3, 3) body-to-world.
            wind: optional (W, 3) m/s: the ambient air, so that each target's rotors and airframe see
                its velocity relative to the air (the wake's share is the same in still air otherwise).
            compiled: the compiled pass (`sim.fields.shed_kernels.forces`); False: the NumPy reference.

        Returns:
            The wake's share of each target's rotor thrust change and airframe drag, mass-normalised;
            the diagonal (a vehicle's own wake) and every pair without a wake exactly 0.
        """
        if not compiled:
            return self._forces_reference(state, pos, vel, rot, wind)
        W, V, _ = self._check_state(state)
        args = dict(pos=_array("pos", pos, (W, V, 3), False), vel=_array("vel", vel, (W, V, 3), False),
                    rot=_array("rot", rot, (W, V, 3, 3), False),
                    wind=_STILL if wind is None else _array("wind", wind, (W, 3), False))
        c, out = self._compiled, np.empty((W, V, V, 3))
        bad = _kernels.forces(state.pos, state.axis, state.depth, state.thrust, state.age, state.valid, state.cursor,
                              *args.values(), self._kinds(V), c["pair"], c["ring_cos"], c["ring_sin"], _TINY, out)
        if bad:
            raise ConfigError(f"{list(args)[bad - 1]}: must be finite")
        return out

    def _forces_reference(self, state: WakeState, pos: Any, vel: Any, rot: Any, wind: Any = None) -> np.ndarray:
        """The readable reference of `forces` (NumPy), the same arguments."""
        W, V, _ = self._check_state(state)
        pos, vel = _array("pos", pos, (W, V, 3)), _array("vel", vel, (W, V, 3))
        rot = _array("rot", rot, (W, V, 3, 3))
        v_rel = vel if wind is None else vel - _array("wind", wind, (W, 3))[:, None, :]
        loc = nearest(state, pos, rot, pos)  # (W, Vs, Vt, ...)
        keep = loc.active & ~np.eye(V, dtype=bool)  # pairs in a wake; a vehicle's own wake left out
        K = self.law.ring_points
        azimuth = (np.arange(K) + 0.5) * (2.0 * math.pi / K)  # the law's ring, from the body x axis
        target = lambda x: np.broadcast_to(x[:, None], (W, V) + x.shape[1:])  # (W, Vt, ...) -> (W, Vs, Vt, ...)
        n_b, x_b, y_b, v_b = target(rot[..., 2]), target(rot[..., 0]), target(rot[..., 1]), target(v_rel)
        out = np.zeros((W, V, V, 3))
        for law, mask in self._pairs:  # each pair of kinds on its (M,) pairs in a wake
            sel = keep if mask is None else keep & mask
            if not sel.any():
                continue
            part = _Local(*(x[sel] for x in loc))
            ring_speed = air = None
            if law.rotors:
                tangent = part.tangent[:, None, :]
                ring_dir = np.cos(azimuth)[:, None] * x_b[sel][:, None] + np.sin(azimuth)[:, None] * y_b[sel][:, None]
                ring_dir = ring_dir - _dot(ring_dir, tangent)[..., None] * tangent  # at the centre's depth
                ring = part.offset[:, None] + float(law.follower_arm) * ring_dir  # (M, K, 3) m from c
                s, T = part.s[:, None], part.thrust[:, None]
                axial, radial = law.induced_velocity(s, _dot(ring, ring), T)
                at_ring = _Local(s, T, part.axis[:, None], tangent, ring, part.active[:, None])
                ring_speed = -_dot(_air(axial, radial, at_ring, ring), n_b[sel][:, None])  # m/s down through each
            if law.drag:
                axial, radial = law.induced_velocity(part.s, _dot(part.offset, part.offset), part.thrust)
                air = _air(axial, radial, part, part.offset)
            out[sel] = law.follower_response(n_b[sel], v_b[sel], ring_speed, air)
        return out

    # ------------------------------------------------------------------ helpers
    def _per_source(self, fn, *arrays):
        """fn(source, *arrays) with each vehicle's (axis 1) own kind's `_Source`; arrays (W, V, ...)."""
        if self._kind_of is None:
            return fn(self._sources[0], *arrays)
        results = None
        for k, src in enumerate(self._sources):
            idx = np.flatnonzero(self._kind_of == k)
            part = fn(src, *(a[:, idx] for a in arrays))
            part = part if isinstance(part, tuple) else (part,)
            if results is None:
                results = tuple(np.empty(arrays[0].shape[:2] + p.shape[2:]) for p in part)
            for r, p in zip(results, part):
                r[:, idx] = p
        return results if len(results) > 1 else results[0]

    def _check_vehicles(self, V: int) -> None:
        if self.vehicles and len(self.vehicles) != V:
            raise ConfigError(f"vehicles: {len(self.vehicles)} kinds for {V} vehicles")

    def _check_state(self, state: Any) -> tuple[int, int, int]:
        if not isinstance(state, WakeState):
            raise ConfigError(f"state: expected a WakeState (ShedWake.initial_state), got {type(state).__name__}")
        W, V, N = state.shape
        if N != self._n:
            raise ConfigError(f"state: {N} elements per vehicle, this wake keeps {self._n} (rate_hz * max_age)")
        self._check_vehicles(V)
        return W, V, N


def _array(name: str, x: Any, shape: tuple[int, ...], finite: bool = True) -> np.ndarray:
    """x as a finite float64 array of exactly `shape`, else ConfigError naming it and the shape; C-contiguous
    (what the compiled passes are compiled for). finite=False leaves the finiteness to the compiled pass."""
    a = np.ascontiguousarray(x, dtype=np.float64)
    if a.shape != shape:
        letters = {3: "(W, V, 3)", 4: "(W, V, 3, 3)", 2: "(W, V)"}
        want = "(W, 3)" if name == "wind" else letters.get(len(shape), "")
        raise ConfigError(f"{name}: expected {want} = {shape} but found {a.shape}")
    if finite and not np.all(np.isfinite(a)):
        raise ConfigError(f"{name}: must be finite")
    return a
