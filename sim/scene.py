"""Build a scene of N quadrotors from `assets/quad.xml` (MjSpec attach with prefixes).

Names are resolved to indices once, here; everything downstream uses the
`Scene`'s index arrays, never string lookups in a loop.

Each vehicle is of a kind (`downwash_core.vehicles`, `kinds=`), the paper quad by default.
A `paper_quad` is `assets/quad.xml` as written (so a default scene is the same model, byte
for byte, as before kinds existed); any other kind is that file with the kind's numbers
written over before it is attached (`apply_kind`): the body's mass and inertia, the rotor
sites and the drawn arms and propellers, and each rotor actuator's thrust limit, motor lag
and yaw moment. The simulator flies each vehicle with its kind's numbers (`sim.vehicle_params`).
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

import mujoco
import numpy as np

from downwash_core.errors import ConfigError, DataError
from downwash_core.params import GRAVITY, RATES, Rates
from downwash_core.roles import DEFAULT_VEHICLES, MAX_VEHICLES, MIN_VEHICLES, Role
from downwash_core.vehicles import DEFAULT_VEHICLE, PAPER_QUAD, VehicleKind, get_vehicle

__all__ = ["QUAD_XML", "DEFAULT_VEHICLES", "Scene", "apply_kind", "build_scene", "check_clearance", "load_quad_spec",
           "resolve_kinds"]

QUAD_XML = Path(__file__).resolve().parent.parent / "assets" / "quad.xml"

# Names inside assets/quad.xml (one place).
_BODY = "quad"
_JOINT = "root"
_ROTORS = ("rotor0", "rotor1", "rotor2", "rotor3")
_ARMS = ("arm0", "arm1", "arm2", "arm3")  # drawn only (class visual)
_PROPS = ("prop0", "prop1", "prop2", "prop3")
_HULL = "hull"


@dataclass(frozen=True)
class Scene:
    """A compiled scene and the indices the simulation needs.

    body_ids: (V,) body id of each vehicle.
    qpos_adr: (V,) start of each vehicle's free joint in qpos (pos 3, quat 4).
    qvel_adr: (V,) start of each vehicle's free joint in qvel (lin vel world 3, ang vel body 3).
    act_ids: (V, 4) actuator (= act and ctrl) index of each rotor.
    kinds: (V,) each vehicle's kind (`downwash_core.vehicles.VehicleKind`).
    """

    model: mujoco.MjModel
    vehicles: tuple[str, ...]
    roles: tuple[Role, ...]
    body_ids: np.ndarray
    qpos_adr: np.ndarray
    qvel_adr: np.ndarray
    act_ids: np.ndarray
    quad_xml_sha256: str = ""  # of the vehicle MJCF the scene was built from (provenance)
    kinds: tuple[VehicleKind, ...] = ()

    def describe(self) -> dict:
        """Vehicles, roles and the vehicle model's digest (provenance); the kinds too unless all are
        the paper quad (so a default scene's provenance is what it was before kinds existed)."""
        out = {"vehicles": list(self.vehicles), "roles": [r.value for r in self.roles],
               "quad_xml_sha256": self.quad_xml_sha256, "timestep": float(self.model.opt.timestep)}
        if any(k != PAPER_QUAD for k in self.kinds):
            out["kinds"] = [k.describe() for k in self.kinds]
        return out

    @property
    def n_vehicles(self) -> int:
        return len(self.vehicles)

    def index(self, role: Role) -> int:
        """The index of the first vehicle with `role`; ConfigError when the scene has none."""
        for i, r in enumerate(self.roles):
            if r == role:
                return i
        raise ConfigError(f"the scene {dict(zip(self.vehicles, self.roles))} has no {Role(role).value}")

    @property
    def leader(self) -> int:
        """Index of the (first) leader, Alpha in the paper."""
        return self.index(Role.LEADER)

    @property
    def follower(self) -> int:
        """Index of the (first) follower, Bravo in the paper."""
        return self.index(Role.FOLLOWER)


def load_quad_spec(path: str | Path = QUAD_XML) -> mujoco.MjSpec:
    """Parse the vehicle MJCF; a missing or malformed file raises a clear error naming it."""
    path = Path(path)
    if not path.is_file():
        raise DataError(f"quadrotor model not found: {path}")
    try:
        spec = mujoco.MjSpec.from_file(str(path))
    except ValueError as e:  # mujoco reports XML parse errors as ValueError
        raise DataError(f"{path}: malformed quadrotor MJCF: {e}") from e
    if spec.body(_BODY) is None:
        raise DataError(f"{path}: expected a body named '{_BODY}' (the vehicle root)")
    for name in _ROTORS:
        if spec.actuator(name) is None:
            raise DataError(f"{path}: expected actuator '{name}' (one per rotor: {', '.join(_ROTORS)})")
    return spec


def resolve_kinds(kinds: Any, n_vehicles: int) -> tuple[VehicleKind, ...]:
    """One `VehicleKind` per vehicle from `kinds`: None (all the paper quad), one name or kind (all
    of it), or a sequence of names or kinds, one per vehicle; ConfigError naming what is allowed."""
    if kinds is None:
        kinds = DEFAULT_VEHICLE
    if isinstance(kinds, (str, VehicleKind)):
        return (get_vehicle(kinds),) * n_vehicles
    try:
        kinds = list(kinds)
    except TypeError:
        raise ConfigError(f"kinds: expected a vehicle name, a VehicleKind or one per vehicle, got {kinds!r}") from None
    if len(kinds) != n_vehicles:
        raise ConfigError(f"kinds: expected one per vehicle ({n_vehicles}), got {len(kinds)}: {kinds}")
    return tuple(get_vehicle(k) for k in kinds)


def apply_kind(quad: mujoco.MjSpec, kind: VehicleKind) -> mujoco.MjSpec:
    """Write `kind`'s numbers over the vehicle spec `quad` (in place; returns it).

    Body: mass and inertia. Rotor sites at the kind's rotor positions (X configuration).
    Actuators: ctrlrange and actrange [0, max_rotor_thrust], the motor lag (dynprm[0]) and
    the yaw moment (gear[5] = spin x yaw_moment_coeff). Drawn geometry: the arms to the
    rotors, the propeller discs at the rotor radius, and the hull (massless; contacts are
    off) scaled with the arm. The sign of each rotor's spin is the file's.
    """
    params = kind.params
    body = quad.body(_BODY)
    body.mass = float(kind.mass)
    body.inertia = [float(x) for x in kind.inertia]
    scale = kind.arm_length / _file_arm_length(quad)
    hull = quad.geom(_HULL)
    if hull is not None:
        hull.size = [float(x) * scale for x in hull.size]
    for k, (rotor, arm, prop) in enumerate(zip(_ROTORS, _ARMS, _PROPS)):
        pos = [float(x) for x in params.rotor_positions[k]]
        quad.site(rotor).pos = pos
        geom = quad.geom(arm)
        if geom is not None:
            geom.fromto = [0.0, 0.0, 0.0, *pos]
            geom.size = [float(geom.size[0]) * scale, *geom.size[1:]]
        geom = quad.geom(prop)
        if geom is not None:
            geom.pos = [pos[0], pos[1], float(geom.pos[2]) * scale]
            geom.size = [float(kind.rotor_radius), *geom.size[1:]]
        act = quad.actuator(rotor)
        act.ctrlrange = [0.0, float(kind.max_rotor_thrust)]
        act.actrange = [0.0, float(kind.max_rotor_thrust)]
        dynprm = list(act.dynprm)
        dynprm[0] = float(kind.motor_time_constant)
        act.dynprm = dynprm
        gear = list(act.gear)
        gear[5] = float(np.sign(gear[5]) or params.rotor_spin[k]) * float(kind.yaw_moment_coeff)
        act.gear = gear
    return quad


def _file_arm_length(quad: mujoco.MjSpec) -> float:
    """m, the vehicle file's arm length (the first rotor site's distance from the body axis)."""
    return float(np.hypot(*quad.site(_ROTORS[0]).pos[:2]))


def build_scene(
    vehicles: Sequence[tuple[str, Role] | str] = DEFAULT_VEHICLES,
    quad_xml: str | Path = QUAD_XML,
    rates: Rates = RATES,
    kinds: str | VehicleKind | Sequence[str | VehicleKind] | None = None,
) -> Scene:
    """Compile a scene with one quadrotor per vehicle (prefix `name/`), a ground plane and cameras.

    vehicles: (name, role) pairs in scene order, or plain names (the first is then the
    leader, the others followers).
    kinds: each vehicle's kind (`downwash_core.vehicles`): None for the paper quad (the
    vehicle file as written), one name or `VehicleKind` for all, or one per vehicle. A
    kind other than `paper_quad` is the vehicle file with the kind's numbers written over
    (`apply_kind`).
    """
    pairs = [(v, Role.LEADER if i == 0 else Role.FOLLOWER) if isinstance(v, str) else (v[0], Role(v[1]))
             for i, v in enumerate(vehicles)]
    roles = tuple(r for _, r in pairs)
    vehicles = tuple(n for n, _ in pairs)
    if not MIN_VEHICLES <= len(vehicles) <= MAX_VEHICLES:
        raise ConfigError(f"vehicles: a scene holds {MIN_VEHICLES}-{MAX_VEHICLES} vehicles, got {len(vehicles)}")
    if len(set(vehicles)) != len(vehicles):
        raise ConfigError(f"vehicles: expected distinct names, got {vehicles}")
    resolved = resolve_kinds(kinds, len(vehicles))
    for kind in resolved:
        if not kind.motor_time_constant > rates.physics_dt:
            raise ConfigError(f"vehicle {kind.name!r}: motor_time_constant {kind.motor_time_constant} s: allowed "
                              f"above the physics step, {rates.physics_dt} s")
    quad = load_quad_spec(quad_xml)

    spec = mujoco.MjSpec()
    spec.modelname = "downwash_scene"
    spec.option.timestep = rates.physics_dt
    spec.option.gravity = [0.0, 0.0, -GRAVITY]
    # No contact dynamics: a flight ends at the first collision with the ground or the other
    # vehicle (sim.simulator checks the geometry), so contacts would never be resolved; the
    # collision pipeline was half the cost of a physics step.
    spec.option.disableflags |= mujoco.mjtDisableBit.mjDSBL_CONTACT
    spec.visual.global_.offwidth = 640
    spec.visual.global_.offheight = 480
    world = spec.worldbody
    world.add_geom(name="ground", type=mujoco.mjtGeom.mjGEOM_PLANE, size=[20, 20, 0.1], rgba=[0.55, 0.6, 0.55, 1])
    world.add_light(name="sun", pos=[0, 0, 6], dir=[0, 0, -1], type=mujoco.mjtLightType.mjLIGHT_DIRECTIONAL)
    for i, (name, kind) in enumerate(zip(vehicles, resolved)):
        frame = world.add_frame(pos=[0.0, 1.0 * i, 1.0])
        child = quad.copy()  # a copy: attach consumes its child
        if kind != PAPER_QUAD:  # the paper quad is the file as written
            apply_kind(child, kind)
        spec.attach(child, prefix=f"{name}/", frame=frame)
    # Overview camera that keeps the first vehicle (the leader) centred; the env moves it.
    world.add_camera(
        name="overview",
        pos=[2.6, -2.6, 2.2],
        mode=mujoco.mjtCamLight.mjCAMLIGHT_TARGETBODY,
        targetbody=f"{vehicles[0]}/{_BODY}",
    )
    try:
        model = spec.compile()
    except ValueError as e:
        raise DataError(f"{quad_xml}: the scene does not compile: {e}") from e

    body_ids = np.array([model.body(f"{v}/{_BODY}").id for v in vehicles])
    joint_ids = [model.joint(f"{v}/{_JOINT}").id for v in vehicles]
    act_ids = np.array([[model.actuator(f"{v}/{r}").id for r in _ROTORS] for v in vehicles])
    return Scene(
        model=model,
        vehicles=vehicles,
        roles=roles,
        body_ids=body_ids,
        qpos_adr=np.array([model.jnt_qposadr[j] for j in joint_ids]),
        qvel_adr=np.array([model.jnt_dofadr[j] for j in joint_ids]),
        act_ids=act_ids,
        quad_xml_sha256=hashlib.sha256(Path(quad_xml).read_bytes()).hexdigest(),
        kinds=resolved,
    )


def check_clearance(pos: np.ndarray, names: Sequence[str], radius_xy: float, radius_z: float) -> None:
    """ConfigError if two vehicles lie inside each other's collision ellipsoid in any world.

    pos: (W, V, 3) or (V, 3) m, world frame (e.g. the references at t = 0); names: the V
    vehicle names (for the message); radius_xy, radius_z: m, the ellipsoid of
    `SimConfig.collision_radius_xy` / `collision_radius_z`, the same test the loop applies.
    """
    pos = np.asarray(pos, dtype=np.float64).reshape(-1, len(names), 3)
    d = pos[:, :, None, :] - pos[:, None, :, :]  # (W, V, V, 3)
    inside = (d[..., 0] ** 2 + d[..., 1] ** 2) / radius_xy**2 + d[..., 2] ** 2 / radius_z**2 < 1.0
    inside &= ~np.eye(len(names), dtype=bool)
    if inside.any():
        w, i, j = (int(x) for x in np.argwhere(inside)[0])
        raise ConfigError(
            f"vehicles {names[i]} and {names[j]} start inside each other in world {w}: {pos[w, i].round(3).tolist()} "
            f"and {pos[w, j].round(3).tolist()} m; allowed: apart by more than the collision ellipsoid "
            f"({radius_xy} m laterally, {radius_z} m vertically)"
        )
