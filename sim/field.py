"""The ground-truth downwash field: a pure, batched force law.

`DownwashField()(p_a, v_a, R_a, p_b, v_b)` is the mean acceleration (m/s^2, world
frame, z up) that the wake of a leader `a` exerts on a follower `b`; turbulence is
not part of it. `pairwise_field` sums it over every leader for N vehicles and works
with any object that has the same call signature (`Field`, the protocol); `pairwise_forces`
keeps the terms of that sum apart, for the aggregation laws of `sim.aggregation`.

The law, with `dp = p_b - p_a` and the leader's axis `n = R_a[..., :, 2]`::

    s      = -dp . n                      depth below the leader along its axis (m)
    r_vec  = dp + s n,  r = |r_vec|       lateral offset from the wake axis (m)
    sigma  = width0 + width_slope s+      wake width (m), s+ = max(s, 0)
    A      = strength / (1 + s+ / strength_depth)^2        on-axis strength (m/s^2)
    w      = smoothstep(fade_start, fade_end, s)           exactly 0 for s <= fade_start
    rho    = r / sigma,  G = exp(-rho^2 / 2)
    vxy    = v_b - (v_b . n) n,  q = |vxy|,  v_r = vxy . r_vec / max(r, eps)
    k      = 1 / (1 + (|v_a,xy| / leader_speed_scale)^2)  v_a,xy = v_a - (v_a . n) n
    down   = A w G (1 - approach_gain tanh(v_r / approach_speed) rho)
    radial = radial_gain A w G (rho^2 - radial_offset (1 + radial_speed_gain q / radial_speed))
    accel  = k (radial r_vec / sigma - down n)

At rest directly below a level leader the force is `(0, 0, -A(s))`: the wake pushes
the follower down (-z), with A = 3.0, 1.4, 0.8 m/s^2 at s = 0.5, 1.0, 1.5 m.
Everything is finite at r = 0, |vxy| = 0 and dp = 0, and no operation divides by zero
or overflows; far outside the wake (rho > ~38) `G` underflows to exactly 0, which
NumPy ignores by default.

The compiled loops over pairs (`DownwashField.pairwise`, `DownwashField.pair_forces`) are
`sim.field_kernels`'.
"""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass
from typing import Any, Callable, Protocol, runtime_checkable

import numpy as np

from downwash_core.errors import ConfigError
from downwash_core.geometry import dot as _dot
from downwash_core import libm
from downwash_core.validate import check_trailing_shapes
# the compiled loops, under the names the fused tick and the tests use
from sim.field_kernels import C4_CORE as _C4_CORE
from sim.field_kernels import pair_forces_kernel as _pair_forces_kernel
from sim.field_kernels import pairwise_kernel as _pairwise_kernel
from sim.stateful_field import check_stateful_field, is_stateful_field

__all__ = ["Field", "DownwashField", "pairwise_field", "pairwise_forces", "check_field", "unit_pair_scale",
           "checked_states", "off_diagonal"]

_EPS = np.array(1e-12)  # m, guards the division by r in v_r (at r = 0, r_vec = 0 so v_r = 0)
# 0-d float64 constants: cheaper per op than Python floats under NumPy 2 promotion.
_ZERO, _ONE, _THREE, _NEG_HALF = (np.array(x) for x in (0.0, 1.0, 3.0, -0.5))
_NEXT, _PREV = [1, 2, 0], [2, 0, 1]  # cross product a x b = a[NEXT] b[PREV] - a[PREV] b[NEXT]


@runtime_checkable
class Field(Protocol):
    """What the simulator calls on a field without memory: the law, through `pairwise_field`.

    ``field(p_a, v_a, R_a, p_b, v_b) -> (..., 3)`` m/s^2, world frame: the mean acceleration of leader
    a's wake on follower b (positions m, velocities m/s, attitudes (..., 3, 3) body to world),
    broadcasting over the leading axes. Optional, found by name: ``pairwise(pos, vel, rot)`` and
    ``pair_forces(pos, vel, rot)`` (faster sums for (W, V, 3) states, None to decline),
    ``describe()`` (its provenance; a dataclass has one from its fields) and ``for_kinds(leader,
    follower)`` (the field of a pair of other vehicle kinds, `sim.fields.kinds.pair_field`).
    A field with memory is a `sim.stateful_field.StatefulField` instead; the simulator takes either.
    """

    def __call__(self, p_a: np.ndarray, v_a: np.ndarray, R_a: np.ndarray, p_b: np.ndarray,
                 v_b: np.ndarray) -> np.ndarray: ...


def _is_off(value: Any) -> bool:
    """True when a knob is a plain Python number equal to 0 (its code path is skipped)."""
    return isinstance(value, (int, float)) and value == 0


@dataclass(frozen=True)
class DownwashField:
    """Mean downwash acceleration of a leader's wake on a follower.

    Every constant may be a float or a NumPy array that broadcasts against the batch
    shape `...` of the inputs (per-world domain randomisation: shape (W,) for inputs
    (W, 3); in `pairwise_field`, whose pair batch is (W, V_leader, V_follower), shape
    (W, 1, 1) per world or (W, V, 1) per leader).

    Misspecification knobs (all 0.0, off, by default; each breaks one assumption of
    the paper's SO(2)-equivariant model class; a knob that is a Python 0 costs nothing):

    c4_amplitude (-, keep |c4| < 1):
        Four-lobe modulation of the vertical force with the leader's yaw,
        ``down *= 1 + c4 cos(4 theta) rho^4 / (rho^4 + 0.5^4)``, where theta is the
        azimuth of r_vec about n measured from the leader's body x axis (for a level
        leader, world azimuth minus leader yaw psi_a), as a quadrotor's four rotors
        would imprint. The taper keeps the field continuous and unchanged on the
        axis. Breaks SO(2) equivariance about n (rotating the follower's state but
        not the leader); C4 (quarter-turn) equivariance remains.
    swirl (-):
        Tangential (swirling) component added to the lateral force,
        ``+ k swirl A w G rho (n x r_vec) / sigma`` (magnitude k swirl A w G rho^2).
        Breaks "the lateral force is radial"; SO(2) equivariance about n is kept,
        since n x (H r) = H (n x r) for any rotation H about n.
    skew (s/m):
        The wake is convected by the leader's lateral velocity: at depth s its axis
        is displaced by ``-skew s+ v_a,xy`` (the wake trails the leader; skew is about
        the inverse of the downwash speed), i.e. ``r_vec += skew s+ v_a,xy``. Breaks
        equivariance whenever v_a,xy != 0, because the group action rotates dp and
        v_b but not v_a; with v_a,xy = 0 nothing changes.
    """

    # Each constant: a float, or an array broadcasting against the batch shape `...`.
    strength: float | np.ndarray = 10.6  # m/s^2, A(s) = strength / (1 + s / strength_depth)^2
    strength_depth: float | np.ndarray = 0.57  # m
    width0: float | np.ndarray = 0.10  # m, sigma = width0 + width_slope * s
    width_slope: float | np.ndarray = 0.12  # -
    fade_start: float | np.ndarray = 0.05  # m, w(s) = smoothstep(fade_start, fade_end, s)
    fade_end: float | np.ndarray = 0.25  # m
    # down = A w G (1 - approach_gain tanh(v_r / approach_speed) rho)
    approach_gain: float | np.ndarray = 1.5  # -
    approach_speed: float | np.ndarray = 0.5  # m/s
    # radial = radial_gain A w G (rho^2 - radial_offset (1 + radial_speed_gain q / radial_speed))
    radial_gain: float | np.ndarray = 0.3  # -
    radial_offset: float | np.ndarray = 1.0  # -, rho^2 of the radial sign change at q = 0
    radial_speed_gain: float | np.ndarray = 0.5  # -, growth of the inward region with q
    radial_speed: float | np.ndarray = 0.5  # m/s
    # k(v_a) = 1 / (1 + (|v_a,xy| / leader_speed_scale)^2)
    leader_speed_scale: float | np.ndarray = 2.0  # m/s
    # Misspecification knobs, off at 0.0 (see the class docstring).
    c4_amplitude: float | np.ndarray = 0.0  # -, four-lobe modulation of the vertical force
    swirl: float | np.ndarray = 0.0  # -, tangential lateral component
    skew: float | np.ndarray = 0.0  # s/m, wake axis displaced by -skew * s * v_a,xy

    def __post_init__(self) -> None:
        # Derived constants, computed once and stored as float64 arrays (0-d for a
        # scalar: an array op with a 0-d array costs ~0.6 us less than with a Python
        # float). Frozen dataclass: set through object.__setattr__.
        f = lambda value: np.asarray(value, dtype=np.float64)  # noqa: E731
        depth = f(self.strength_depth)
        inv_fade = 1.0 / (f(self.fade_end) - f(self.fade_start))
        radial_gain = f(self.radial_gain)
        speed2 = f(self.leader_speed_scale) ** 2
        derived = {
            # k A = strength depth^2 scale^2 / ((depth + s)^2 (scale^2 + |v_a,xy|^2))
            "_kA_numerator": f(self.strength) * depth * depth * speed2,
            "_depth": depth,
            "_speed2": speed2,
            # sigma = width0 - width_slope * min(h, 0), h = -s
            "_width0": f(self.width0),
            "_neg_width_slope": -f(self.width_slope),
            # smoothstep argument t = (s - fade_start) / (fade_end - fade_start)
            "_neg_inv_fade": -inv_fade,
            "_fade_offset": f(self.fade_start) * inv_fade,
            "_approach_gain": f(self.approach_gain),
            "_inv_approach_speed": 1.0 / f(self.approach_speed),
            # radial = radial_gain A w G (rho^2 - offset - offset speed_gain q / speed)
            "_radial_gain": radial_gain,
            "_radial_c0": radial_gain * f(self.radial_offset),
            "_radial_cq": radial_gain * f(self.radial_offset) * f(self.radial_speed_gain)
            / f(self.radial_speed),
            "_c4": None if _is_off(self.c4_amplitude) else f(self.c4_amplitude),
            "_swirl": None if _is_off(self.swirl) else f(self.swirl),
            "_skew": None if _is_off(self.skew) else f(self.skew),
        }
        for name, value in derived.items():
            object.__setattr__(self, name, value)
        scalars = all(np.ndim(getattr(self, f.name)) == 0 for f in dataclasses.fields(self))
        object.__setattr__(
            self, "_packed",
            np.array([float(getattr(self, f.name)) for f in dataclasses.fields(self)]) if scalars else None,
        )

    @property
    def packed(self) -> np.ndarray | None:
        """(16,) float64: the constants in declaration order, as the compiled kernels (and the fused
        tick) read them; None with per-world constants."""
        return self._packed

    def pairwise(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray,
                 scale: np.ndarray | None = None) -> np.ndarray | None:
        """Compiled `pairwise_field(self, ...)` for (W, V, 3) inputs; None with per-world constants.

        Same law as `__call__`, evaluated in one loop over worlds and ordered pairs
        (the autopilot-rate hot path: NumPy's per-call overhead dominates on small batches).
        scale: (V_leader, V_follower) factors of each pair's strength (None: all 1; the pairs of
        vehicle kinds, `sim.vehicle_params.KindPairs`).
        """
        if self._packed is None:
            return None
        if scale is None:
            scale = unit_pair_scale(pos.shape[1])
        return _pairwise_kernel(pos, vel, rot, self._packed, scale)  # strided views as they are

    def pair_forces(self, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray,
                    scale: np.ndarray | None = None) -> np.ndarray | None:
        """Compiled `pairwise_forces(self, ...)` for (W, V, 3) inputs; None with per-world constants.

        pos, vel (W, V, 3) m, m/s and rot (W, V, 3, 3), world frame; scale as in `pairwise`. Returns
        (W, V_leader, V_follower, 3) m/s^2: every ordered pair's force, 0 on the diagonal;
        summed over leaders it is `pairwise(...)` up to rounding (bit for bit for V = 2).
        """
        if self._packed is None:
            return None
        if scale is None:
            scale = unit_pair_scale(pos.shape[1])
        return _pair_forces_kernel(pos, vel, rot, self._packed, scale)

    def __call__(
        self,
        p_a: np.ndarray,
        v_a: np.ndarray,
        R_a: np.ndarray,
        p_b: np.ndarray,
        v_b: np.ndarray,
        *,
        validate: bool = False,
    ) -> np.ndarray:
        """Mean wake acceleration on the follower (no turbulence).

        Args:
            p_a: (..., 3) m, world frame, leader position.
            v_a: (..., 3) m/s, world frame, leader velocity.
            R_a: (..., 3, 3) leader attitude, body-to-world; its axis is R_a[..., :, 2].
            p_b: (..., 3) m, world frame, follower position.
            v_b: (..., 3) m/s, world frame, follower velocity.
            validate: check the shapes first and raise ValueError naming the argument
                (off by default: this runs at 100 Hz).

        Returns:
            (..., 3) m/s^2, world frame, float64: the mass-normalised force on the
            follower, `...` the broadcast of the inputs' batch shapes.
        """
        if validate:
            p_a, v_a, R_a, p_b, v_b = (np.asarray(x) for x in (p_a, v_a, R_a, p_b, v_b))
            check_trailing_shapes(
                {"p_a": p_a.shape, "v_a": v_a.shape, "R_a": R_a.shape,
                 "p_b": p_b.shape, "v_b": v_b.shape},
                {"p_a": (3,), "v_a": (3,), "R_a": (3, 3), "p_b": (3,), "v_b": (3,)},
            )
        n = R_a[..., :, 2]
        dp = p_b - p_a
        h = _dot(dp, n)  # m, height above the leader along n (= -s)
        r_vec = dp - h[..., None] * n
        neg_s_pos = np.minimum(h, _ZERO)  # -max(s, 0): A and sigma stay finite above

        # Leader's lateral speed: wake weakening k and (optionally) skew.
        va_n = _dot(v_a, n)
        if self._skew is None:
            va2 = _dot(v_a, v_a) - va_n * va_n
        else:
            va_xy = v_a - va_n[..., None] * n
            va2 = _dot(va_xy, va_xy)
            r_vec = r_vec - (self._skew * neg_s_pos)[..., None] * va_xy

        # Follower's lateral velocity and offset from the wake axis.
        vxy = v_b - _dot(v_b, n)[..., None] * n
        q = np.sqrt(_dot(vxy, vxy))
        r = np.sqrt(_dot(r_vec, r_vec))
        v_r = _dot(vxy, r_vec) / np.maximum(r, _EPS)

        sigma = self._width0 + self._neg_width_slope * neg_s_pos
        inv_sigma = np.reciprocal(sigma)
        rho = r * inv_sigma
        rho2 = rho * rho
        t = np.minimum(np.maximum(h * self._neg_inv_fade - self._fade_offset, _ZERO), _ONE)
        depth_s = self._depth - neg_s_pos
        # k A w G, with w = t^2 (3 - 2 t): exactly 0 for s <= fade_start.
        kawg = (
            (self._kA_numerator * (t * t) * (_THREE - (t + t)) * libm.exp(rho2 * _NEG_HALF))
            / ((depth_s * depth_s) * (self._speed2 + va2))
        )

        down = kawg - kawg * (self._approach_gain * rho) * libm.tanh(v_r * self._inv_approach_speed)
        if self._c4 is not None:
            # cos(4 theta) r^4 = x^4 - 6 x^2 y^2 + y^4 = (x^2 + y^2)^2 - 8 x^2 y^2, with
            # (x, y) the components of r_vec along the leader's body x and y axes;
            # taper r^4 / (r^4 + (0.5 sigma)^4) = rho^4 / (rho^4 + 0.5^4).
            x = _dot(r_vec, R_a[..., :, 0])
            y = _dot(r_vec, R_a[..., :, 1])
            x2, y2 = x * x, y * y
            r4 = (x2 + y2) * (x2 + y2)
            core2 = _C4_CORE * _C4_CORE * (sigma * sigma)
            down = down + (self._c4 * down) * (r4 - 8.0 * x2 * y2) / (r4 + core2 * core2)
        # radial / sigma: the coefficient of r_vec
        radial = (self._radial_gain * rho2 - self._radial_c0 - self._radial_cq * q) * (
            kawg * inv_sigma
        )

        accel = radial[..., None] * r_vec - down[..., None] * n
        if self._swirl is not None:
            n_x_r = n[..., _NEXT] * r_vec[..., _PREV] - n[..., _PREV] * r_vec[..., _NEXT]
            accel = accel + (self._swirl * kawg * rho * inv_sigma)[..., None] * n_x_r
        return accel


def pairwise_field(
    field: Callable[..., np.ndarray],
    pos: np.ndarray,
    vel: np.ndarray,
    rot: np.ndarray,
) -> np.ndarray:
    """Total wake force on every vehicle from all the others.

    Args:
        field: any callable `field(p_a, v_a, R_a, p_b, v_b) -> (..., 3)` with
            `DownwashField`'s signature and broadcasting (pluggable).
        pos: (..., V, 3) m, world frame, vehicle positions.
        vel: (..., V, 3) m/s, world frame, vehicle velocities.
        rot: (..., V, 3, 3) body-to-world attitudes.

    Returns:
        (..., V, 3) m/s^2, world frame: for each follower j,
        sum over leaders i != j of field(p_i, v_i, R_i, p_j, v_j).

    A field may offer `field.pairwise(pos, vel, rot)` for (W, V, ...) inputs, a faster
    evaluation of exactly this sum (or None to decline); `DownwashField` has a compiled
    one for scalar constants, tested against this broadcast evaluation.

    The field is evaluated once on the (..., V_leader, V_follower) pair batch, the
    diagonal included (dp = 0; its values, even if not finite, are discarded), so
    per-world field constants need shape (W, 1, 1) here.
    """
    fast = getattr(field, "pairwise", None)
    if fast is not None and type(pos) is np.ndarray and pos.ndim == 3 and pos.shape[2] == 3:
        # the loop's hot path (100 Hz): one shape comparison, then the compiled sum
        if getattr(vel, "shape", None) == pos.shape and getattr(rot, "shape", None) == pos.shape + (3,):
            result = fast(pos, vel, rot)
            if result is not None:
                return result
    pos, vel, rot, n_veh = checked_states(pos, vel, rot)
    # Leaders i along axis -3, followers j along axis -2 of the (..., i, j, 3) result.
    forces = field(
        pos[..., :, None, :],
        vel[..., :, None, :],
        rot[..., :, None, :, :],
        pos[..., None, :, :],
        vel[..., None, :, :],
    )
    return np.where(off_diagonal(n_veh), forces, 0.0).sum(axis=-3)


def pairwise_forces(
    field: Callable[..., np.ndarray],
    pos: np.ndarray,
    vel: np.ndarray,
    rot: np.ndarray,
) -> np.ndarray:
    """Every ordered pair's wake force, kept apart (the terms of `pairwise_field`'s sum).

    Args: as `pairwise_field`.

    Returns:
        (..., V_leader, V_follower, 3) m/s^2, world frame: [..., i, j, :] is
        field(p_i, v_i, R_i, p_j, v_j), exactly 0 on the diagonal i = j.

    A field may offer `field.pair_forces(pos, vel, rot)` for (W, V, ...) inputs (or
    None to decline); `DownwashField` has a compiled one for scalar constants.
    Otherwise the field is evaluated once on the broadcast pair batch, as in
    `pairwise_field`.
    """
    fast = getattr(field, "pair_forces", None)
    if fast is not None and type(pos) is np.ndarray and pos.ndim == 3 and pos.shape[2] == 3:
        if getattr(vel, "shape", None) == pos.shape and getattr(rot, "shape", None) == pos.shape + (3,):
            result = fast(pos, vel, rot)
            if result is not None:
                return result
    pos, vel, rot, n_veh = checked_states(pos, vel, rot)
    forces = field(
        pos[..., :, None, :],
        vel[..., :, None, :],
        rot[..., :, None, :, :],
        pos[..., None, :, :],
        vel[..., None, :, :],
    )
    return np.where(off_diagonal(n_veh), forces, 0.0)


def checked_states(pos: Any, vel: Any, rot: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
    """(pos, vel, rot, V) as arrays; ConfigError unless (..., V, 3), (..., V, 3), (..., V, 3, 3)."""
    pos, vel, rot = np.asarray(pos), np.asarray(vel), np.asarray(rot)
    if pos.ndim < 2 or pos.shape[-1] != 3:
        raise ConfigError(f"pos: expected (..., V, 3) but found {pos.shape}")
    n_veh = pos.shape[-2]
    if vel.shape[-2:] != (n_veh, 3):
        raise ConfigError(f"vel: expected (..., {n_veh}, 3) like pos but found {vel.shape}")
    if rot.shape[-3:] != (n_veh, 3, 3):
        raise ConfigError(f"rot: expected (..., {n_veh}, 3, 3) like pos but found {rot.shape}")
    if not (pos.shape[:-2] == vel.shape[:-2] == rot.shape[:-3]):
        check_trailing_shapes(
            {"pos": pos.shape, "vel": vel.shape, "rot": rot.shape},
            {"pos": (n_veh, 3), "vel": (n_veh, 3), "rot": (n_veh, 3, 3)},
        )
    return pos, vel, rot, n_veh


@functools.lru_cache(maxsize=None)
def off_diagonal(n_veh: int) -> np.ndarray:
    """(V, V, 1) read-only bool mask, False where leader == follower."""
    mask = ~np.eye(n_veh, dtype=bool)[:, :, None]
    mask.flags.writeable = False
    return mask


@functools.lru_cache(maxsize=None)
def unit_pair_scale(n_veh: int) -> np.ndarray:
    """(V, V) ones: the per-pair strength factors of a field flown as given (never written to;
    writeable, so that the kernels see one array type whatever the caller)."""
    return np.ones((n_veh, n_veh))


def check_field(field: Any, pos: np.ndarray | None = None, vel: np.ndarray | None = None,
                rot: np.ndarray | None = None, name: str | None = None, finite: bool = True) -> None:
    """ConfigError unless `field` returns (W, V, 3) accelerations through `pairwise_field`, finite
    unless `finite` is False.

    Called once before any flight: by `--field` and the envs' `field=` on two small scenes
    (a follower 0.6 m below a level leader, at rest and moving, one slightly off the
    axis), and by the `Simulator` on its own starting states for the shape (a NaN that
    appears in flight ends that world as diverged). So a field of the wrong signature,
    shape or with NaN output is named before it can corrupt a batch of flights.
    pos, vel (W, V, 3) m, m/s and rot (W, V, 3, 3), world frame.
    """
    label = name or type(field).__name__
    if pos is None:
        pos = np.array([[[0.0, 0.0, 2.5], [0.0, 0.0, 1.9]], [[0.1, -0.2, 2.4], [0.25, 0.0, 1.7]]])
        vel = np.array([[[0.0, 0.0, 0.0], [0.0, 0.0, 0.0]], [[0.3, 0.0, 0.0], [0.0, 0.5, -0.1]]])
        rot = np.broadcast_to(np.eye(3), (2, 2, 3, 3)).copy()
    if is_stateful_field(field):  # a field with memory: a few steps of its wake instead of one call
        return check_stateful_field(field, pos, vel, rot, label, finite)
    if not callable(field):
        raise ConfigError(f"{label}: a field must be callable as field(p_a, v_a, R_a, p_b, v_b), got {type(field).__name__}")
    try:
        out = np.asarray(pairwise_field(field, pos, vel, rot))
    except (TypeError, ValueError, IndexError) as e:
        raise ConfigError(f"{label}: calling it as field(p_a, v_a, R_a, p_b, v_b) on (..., 3) arrays failed: "
                          f"{type(e).__name__}: {e}") from e
    if out.shape != pos.shape:
        raise ConfigError(f"{label}: expected accelerations of shape (..., 3) broadcast over the inputs, got "
                          f"{out.shape} from pairwise_field for inputs of shape {pos.shape}")
    if finite and not np.all(np.isfinite(out)):
        raise ConfigError(f"{label}: returned non-finite accelerations (m/s^2) for followers near a leader: {out.tolist()}")
