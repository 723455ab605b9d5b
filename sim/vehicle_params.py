"""Each vehicle's own numbers for the loop, and the one place where a wake scales with its pair of vehicles.

A scene's vehicles are each of a kind (`sim.scene.build_scene(kinds=...)`, `downwash_core.vehicles`;
the paper quad by default); a `Scene` without kinds flies `SimConfig.quad` for every vehicle.
`VehicleParams.of(scene, config)` turns them into the arrays the loop's kernels read, one entry per
vehicle (V,) or per ordered pair (V_leader, V_follower):

| array | shape | what | read by |
|---|---|---|---|
| `mass` | (V,) kg | the field's and the wind's accelerations into forces; the controller's model at start | `actuate_kernel`, `wind_force_kernel` |
| `drag_gain` | (V,) 1/m | the wind's drag, rho C_d A_ref a / (2 m), a = `airframe_area_scale` | `wind_sense_kernel` |
| `hover_thrust` | (V,) N | each rotor's thrust at reset (a level hover) | `Simulator.reset` |
| `Autopilot.tables` | (V, 14, 4), (V,) N | the attitude loop through each vehicle's inertia, mixer and rotor limit | `actuate_kernel` |
| `field_scale` | (V, V) - | the paper's law's factor per pair, `so2_pair_scale` | `sim.field_kernels.pairwise_kernel` |
| `collision_xy`, `collision_z` | (V, V) m | `SimConfig`'s ellipsoid (two paper quads') times the pair's mean `size_scale` | `status_kernel` |

The numbers are per vehicle and the same in every world: the envs' per-episode randomisation
(`downwash_envs.engine.VehicleModel`) changes the worlds' true bodies through
`Physics.set_body_mass` and keeps these nominal ones, as the controller's model does (its
believed mass, `Simulator._mass_believed`, is (W, V)).

Wakes between kinds. The fields are set for a paper quad in a paper quad's wake; `pair_field(field,
leader, follower)` is the field for one ordered pair (docs/fields.md, "Vehicles of other kinds"; it
lives in `sim.fields.kinds`, beside the fields that build on it, and is re-exported here):

- `sim.field.DownwashField` (so2): strength x `so2_pair_scale(leader, follower)` =
  (m_l / m_f) min(1, A_f / A_l): the leader's disc loading sets the wake's dynamic pressure, the
  follower feels it on the part of its rotor discs inside the wake, per kilogram;
- `sim.fields.momentum.MomentumWake`: the leader's mass and rotors, the follower's mass, rotors and
  arm from `momentum_wake_kwargs`, the airframe's drag area x `momentum_drag_area_scale`;
- any other field: its `for_kinds(leader, follower)`, or ConfigError naming these.

A pair of paper quads flies the field as given (the same object); so does every pair whose factor is
exactly 1.0. `scene_field` wraps a field into `KindPairs` (each pair with its own) only where some
pair differs, and `scene_predictor` gives an `OraclePredictor` the scene's pairs the same way: a scene
of paper quads flies, bit for bit, what it flew before kinds existed.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Any, Sequence

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.params import QUAD, QuadParams
from downwash_core.vehicles import airframe_area_scale, as_params, size_scale, so2_pair_scale
from sim.field import DownwashField, checked_states, off_diagonal
from sim.fields.kinds import kind_name, pair_field
from sim.predictor import OraclePredictor, PerWorldPredictor
from sim.stateful_field import is_stateful_field
from sim.wind import AIRFRAME

__all__ = ["VehicleParams", "KindPairs", "pair_field", "scene_field", "scene_predictor", "collision_radii"]


def collision_radii(quads: Sequence[QuadParams], radius_xy: float, radius_z: float) -> tuple[np.ndarray, np.ndarray]:
    """(V, V) m each: the collision ellipsoid of every pair, the radii of two paper quads (`SimConfig`'s)
    times the mean of the two vehicles' `size_scale` (their rotor tips' reach); exactly the given
    radii for two paper quads ((1.0 + 1.0) / 2 = 1.0)."""
    size = np.array([size_scale(q) for q in quads])
    pair = (size[:, None] + size[None, :]) / 2.0
    return radius_xy * pair, radius_z * pair


@dataclasses.dataclass(frozen=True, eq=False)
class VehicleParams:
    """The per-vehicle and per-pair arrays of a scene (see the module table).

    quads: (V,) each vehicle's numbers (plain `QuadParams`); names: (V,) its kind's name.
    """

    quads: tuple[QuadParams, ...]
    names: tuple[str, ...]
    mass: np.ndarray
    drag_gain: np.ndarray
    hover_thrust: np.ndarray
    field_scale: np.ndarray
    collision_xy: np.ndarray
    collision_z: np.ndarray

    @classmethod
    def of(cls, scene: Any, config: Any) -> "VehicleParams":
        """The arrays of `scene`'s vehicles: each of its kind (`scene.kinds`), or all `config.quad` for a
        scene without kinds. ConfigError when `config.quad` is set to a vehicle the scene's kinds
        contradict (`config.quad` is the vehicle of a scene without kinds, the paper quad by default)."""
        V, own = scene.n_vehicles, as_params(config.quad)
        kinds = tuple(scene.kinds) if scene.kinds else (config.quad,) * V
        quads = tuple(as_params(k) for k in kinds)
        if scene.kinds and own != QUAD and any(q != own for q in quads):
            raise ConfigError(
                f"SimConfig.quad: set to {kind_name(own)} (mass {own.mass} kg), not the scene's vehicles of kinds "
                f"{[kind_name(k) for k in kinds]}; each vehicle flies its own kind's numbers: leave SimConfig.quad at "
                "the paper quad (the vehicle of a scene without kinds) or build the scene of that kind "
                "(sim.scene.build_scene(kinds=...))")
        # the wind's drag per unit mass, each airframe's area by geometric similarity (exactly AIRFRAME's
        # for the paper quad: its area x 1.0)
        drag = [dataclasses.replace(AIRFRAME, reference_area=AIRFRAME.reference_area * airframe_area_scale(q))
                for q in quads]
        xy, z = collision_radii(quads, config.collision_radius_xy, config.collision_radius_z)
        return cls(
            quads=quads, names=tuple(kind_name(k) for k in kinds),
            mass=np.array([q.mass for q in quads], dtype=np.float64),
            drag_gain=np.array([d.gain(q.mass) for d, q in zip(drag, quads)], dtype=np.float64),
            hover_thrust=np.array([q.hover_rotor_thrust for q in quads], dtype=np.float64),
            field_scale=np.array([[so2_pair_scale(a, b) for b in quads] for a in quads], dtype=np.float64),
            collision_xy=np.ascontiguousarray(xy), collision_z=np.ascontiguousarray(z),
        )

    @property
    def n_vehicles(self) -> int:
        return len(self.quads)

    def hover_controls(self, act_ids: np.ndarray, n_actuators: int) -> np.ndarray:
        """(n_actuators,) N: every rotor of vehicle i at its hover thrust (act_ids (V, 4), `Scene.act_ids`)."""
        out = np.zeros(n_actuators)
        for i, thrust in enumerate(self.hover_thrust):
            out[act_ids[i]] = thrust
        return out

    def autopilot_tables(self, autopilot: Any) -> tuple[np.ndarray, np.ndarray]:
        """gain (V, 14, 4) and max_thrust (V,) N of `autopilot` for these vehicles (`Autopilot.tables`); an
        object with only `gain` (14, 4) and `max_thrust` flies them for every vehicle."""
        tables = getattr(autopilot, "tables", None)
        if tables is not None:
            return tables(self.quads)
        gain = np.ascontiguousarray(np.broadcast_to(autopilot.gain, (self.n_vehicles, 14, 4)), dtype=np.float64)
        return gain, np.full(self.n_vehicles, float(autopilot.max_thrust))


# ----------------------------------------------------------------------------- wakes between kinds


class KindPairs:
    """A field over a scene of vehicle kinds: every ordered pair with its own field (`pair_field`).

    It offers what `sim.field.pairwise_field` and `pairwise_forces` call on (W, V, 3) states,
    `pairwise` and `pair_forces`. A `DownwashField` of scalar constants runs the compiled kernel with
    the per-pair factors (`VehicleParams.field_scale`), as the fused tick does; any other field is
    evaluated once per distinct pair of kinds on the whole pair batch, each pair taking its own.
    """

    def __init__(self, field: Any, vehicles: VehicleParams):
        self.field = field
        self.scale = vehicles.field_scale
        V = vehicles.n_vehicles
        fields: dict[tuple[QuadParams, QuadParams], Any] = {}
        masks: dict[tuple[QuadParams, QuadParams], np.ndarray] = {}
        for i, a in enumerate(vehicles.quads):
            for j, b in enumerate(vehicles.quads):
                if (a, b) not in fields:
                    fields[a, b], masks[a, b] = pair_field(field, a, b), np.zeros((V, V, 1), bool)
                masks[a, b][i, j] = True
        self.groups = [(fields[key], masks[key]) for key in fields]  # (the pair's field, (V, V, 1) its pairs)
        # a DownwashField of scalar constants whose sums are DownwashField's: its compiled kernels, each
        # pair with its factor
        self._compiled = (isinstance(field, DownwashField) and field.packed is not None
                          and type(field).pairwise is DownwashField.pairwise)

    def describe(self) -> dict[str, Any]:
        from downwash_core.provenance import describe

        return {"type": f"{type(self).__module__}.{type(self).__qualname__}", "field": describe(self.field)}

    def __call__(self, *args: Any, **kwargs: Any) -> np.ndarray:
        raise ConfigError("KindPairs evaluates a whole scene's pairs: call sim.field.pairwise_field(pairs, pos, vel, "
                          "rot) (or its pairwise / pair_forces) with (W, V, 3) states, not one pair")

    def pairwise(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(..., V, 3) m/s^2: on every vehicle, the sum over the others of their pair's field."""
        if self._compiled and pos.ndim == 3:
            return DownwashField.pairwise(self.field, pos, vel, rot, self.scale)
        return self.pair_forces(pos, vel, rot).sum(axis=-3)

    def pair_forces(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray) -> np.ndarray:
        """(..., V_leader, V_follower, 3) m/s^2: every ordered pair's force, its pair's field; 0 on the diagonal."""
        if self._compiled and pos.ndim == 3:
            return DownwashField.pair_forces(self.field, pos, vel, rot, self.scale)
        pos, vel, rot, n_veh = checked_states(pos, vel, rot)
        leaders, followers = (pos[..., :, None, :], vel[..., :, None, :], rot[..., :, None, :, :]), \
            (pos[..., None, :, :], vel[..., None, :, :])
        forces = None
        for field, mask in self.groups:
            f = np.asarray(field(*leaders, *followers), dtype=np.float64)
            forces = np.where(mask, f, 0.0 if forces is None else forces)
        return np.where(off_diagonal(n_veh), forces, 0.0)


def scene_field(field: Any, vehicles: VehicleParams) -> Any:
    """`field` itself when every pair of the scene flies it as given (a scene of paper quads) or when it
    has memory (it takes the kinds itself, `sim.field_memory`), else its `KindPairs`."""
    if is_stateful_field(field):
        return field
    quads = list(dict.fromkeys(vehicles.quads))  # the distinct kinds in scene order
    if all(pair_field(field, a, b) is field for a in quads for b in quads):
        return field
    return KindPairs(field, vehicles)


def scene_predictor(predictor: Any, vehicles: VehicleParams) -> Any:
    """The predictor as it runs in this scene: an `OraclePredictor` (also inside a `PerWorldPredictor`)
    evaluates the scene's pairs as the truth does (`scene_field`); a predictor with a
    ``for_vehicles(kinds)`` method (a learned model that reads the vehicle kinds) is told the
    scene's kinds by name; any other predictor as it is."""
    if type(predictor) is OraclePredictor:
        field = scene_field(predictor.field, vehicles)
        return predictor if field is predictor.field else OraclePredictor(field, predictor.aggregation)
    if type(predictor) is PerWorldPredictor:
        inner = [scene_predictor(p, vehicles) for p in predictor.predictors]
        if all(a is b for a, b in zip(inner, predictor.predictors)):
            return predictor
        out = copy.copy(predictor)
        out.predictors = inner
        return out
    return told_kinds(predictor, vehicles)


def told_kinds(predictor: Any, vehicles: VehicleParams) -> Any:
    """``predictor.for_vehicles(the scene's kind names)`` where it has that method (a learned model
    that reads the vehicle kinds), else the predictor itself."""
    bind = getattr(predictor, "for_vehicles", None)
    return bind(list(vehicles.names)) if callable(bind) else predictor
