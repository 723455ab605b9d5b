"""A safety layer on the commanded accelerations: a control barrier function (CBF) filter.

In a tight vertical stack a vehicle that sags under an under-predicted wake can fall onto the one below. The
filter takes the controller's commanded accelerations u_nom (W, V, 3) m/s^2 of every vehicle of every world
and returns the nearest commands (least squares) that keep, with the double-integrator model p'' = u + f and
the estimated states the controller uses,

- every pair out of its collision ellipsoid inflated by `inflation` (the simulator's own: each pair's lateral
  and vertical radii a, c, `sim.vehicle_params.collision_radii`, handed to the filter when it is built):
  h = q - inflation with q = sqrt((dx^2 + dy^2) / a^2 + dz^2 / c^2), dp = p_i - p_j; the simulator counts a
  collision at q < 1, so the bound is what it checks, scaled. The margin beyond the ellipsoid, (inflation - 1) c
  vertically, is at most `max_margin` m: a larger pair's barrier is its ellipsoid times 1 + max_margin / c, given
  to the filter as radii scaled by that over `inflation` (`barrier_radii`: h then is the inflated one's times a
  constant, the same barrier);
- every vehicle's height: h = z_i - ground_clearance.

Each barrier is of second order (exponential, HOCBF), since a position has relative degree 2:
h'' + k1 h' + k0 h >= 0. With M = diag(1/a^2, 1/a^2, 1/c^2) and dv, da the relative velocity and acceleration,
q^2 = dp.M dp, so q q' = dp.M dv and q q'' = dp.M da + dv.M dv - q'^2: with g = |M dp| and n = M dp / g,

    q' = dp.M dv / q,    q'' = (g / q) n.da + (dv.M dv - q'^2) / q,    da = u_i - u_j + f_i - f_j,

linear in the commands (the sphere's h'' = n.da + (|dv|^2 - (n.dv)^2) / r is the case a = c = 1). Each pair's
row is written with the unit normal n: n.(u_i - u_j) >= -(q / g) (k1 q' + k0 h + (dv.M dv - q'^2) / q) - n.df,
in m/s^2 like the ground's and the box's rows (q / g is a length: c for a pair straight above another, so
there the barrier is the vertical gap's, dz'' + k1 dz' + k0 (dz - inflation c) >= 0). k1 >= 2 sqrt(k0) (real
poles -l1, -l2 of s^2 + k1 s + k0): from a state with h >= 0 and h' + l1 h >= 0 (l1 the smaller root) the
barrier keeps h >= 0, and one control period of constant acceleration keeps it too (tests/test_safety.py).

The drift f is uncertain: f_hat, the controller's held prediction, may under- or mis-predict a wake (a model
outside its data), and then a barrier trusting it lets the stack close. So the filter keeps its own estimate
d of what each vehicle feels, from what it measures at the control rate, as `sim.observer` does:

    d_meas = (v_est(t_k) - v_est(t_k-1)) / dt - u(t_k-1),    d <- d + (1 - exp(-bandwidth dt)) (d_meas - d),

u(t_k-1) the command it let through the tick before as feedback linearisation and the rotors realise it
(`realised`: within the tilt cone, above the thrust floor, below the vehicle's full thrust; a saturated
vehicle's shortfall counted as a disturbance would wind the estimate up, the filter asking ever more of the
vehicle that cannot give it), dt the control period (the first call after a reset only records). Each barrier
takes the more restrictive of the two: for a pair min(n.(f_hat_i - f_hat_j),
n.(d_i - d_j)) in place of n.df, for the ground min(f_hat_z, d_z). Where the model is right both agree up to
the estimate's lag and noise; where it is wrong the measured force still holds the barrier. The estimate lives
in `SafetyFilter.state` ((W, V, STATE_WIDTH): d, the last v_est, the last realised command, whether one was seen), one
row per world and vehicle, cleared by `SafetyFilter.reset` with the simulator's worlds; the fused tick gets it
by address (the C function's last argument), so both paths of the simulator share it.

Pairwise constraints couple the vehicles of a world, so each world is one QP:

    min |u - u_nom|^2  s.t.  A u >= b  (the barriers)  and  lower <= u <= upper  (`actuator_box`)

solved exactly by Goldfarb and Idnani's dual active-set method (1983) for a unit Hessian: it starts at u_nom
and adds the most violated constraint at a time, so a command that violates no barrier (by more than
`TOLERANCE`) comes out unchanged bit for bit. The box is the commands feedback linearisation realises
(`controllers.lqr`: the tilt limit, the floor MIN_THRUST_G, a `thrust_fraction` of each vehicle's full
thrust), widened to include u_nom itself: the filter never clips a command it leaves alone, nor moves one out
of the box. Where the box makes the barriers infeasible together, a barrier that cannot be met with those
already held is left unmet (counted; the vehicles do what their thrust allows), and the solution is brought
back into the widened box (the solver may leave a box row unmet instead, depending on the order it meets
them: the box holds, a command beyond it would not be realised).

Two paths, one algorithm: `SafetyFilter.reference` in NumPy (`np.linalg.solve` on the active normals) and
`cbf_filter_kernel`, compiled (a small Cholesky, no BLAS: the same bits on every CPU), tested equal; the
estimate's update is the same arithmetic on both (`estimate_step`, bit for bit).
`Simulator(..., safety=SafetyConfig())` runs the compiled one on both of its paths (`SafetyFilter.apply`; the
fused tick through `safety_function`, a C function).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import asdict, dataclass
from typing import Any, Sequence

import numpy as np

from controllers.lqr import MAX_TILT_DEG, MIN_THRUST_G, FeedbackLinearisedLQR, attitude_setpoint
from downwash_core.errors import ConfigError
from downwash_core.params import GRAVITY, RATES
from downwash_core.validate import number
from sim.observer import DEFAULT_BANDWIDTH
from sim.safety_kernels import (DEPENDENT, MAX_STEPS, MIN_Q, N_PARAMS, SAFETY_SIGNATURE, STATE_WIDTH, TOLERANCE,
                                cbf_filter_kernel, safety_function)

__all__ = ["SafetyConfig", "SafetyFilter", "safety_filter", "actuator_box", "barrier_radii", "constraint_rows",
           "estimate_step", "record_step", "realised", "pack_params", "solve_qp", "cbf_filter_kernel",
           "SAFETY_SIGNATURE", "safety_function", "TOLERANCE", "DEPENDENT", "N_PARAMS", "STATE_WIDTH"]

# name, unit, lowest, highest, lowest excluded
_RANGES = (("inflation", "-", 1.0, 100.0, False), ("max_margin", "m", 0.0, 100.0, True),
           ("ground_clearance", "m", 0.0, 100.0, False),
           ("k0", "1/s^2", 0.0, 1e4, True), ("k1", "1/s", 0.0, 1e3, True), ("bandwidth", "rad/s", 0.0, 1e3, True),
           ("thrust_fraction", "-", 0.0, 1.0, True))


@dataclass(frozen=True)
class SafetyConfig:
    """The CBF filter's settings (module docstring). Why the defaults are what they are:

    inflation 2.5: between the barrier's surface and a collision lies (inflation - 1) times the pair's
    ellipsoid, and that margin must hold what the filter's model p'' = u + f misses. In crazyflie_stack (the
    tightest preset: four Crazyflies 0.25 m apart, c = 4.3 cm) two Crazyflies' relative acceleration differs
    from the model's by 1 to 3 m/s^2 for 0.1 to 0.3 s: the estimate lags a wake that changes with the geometry,
    the motors lag 30 ms, a vehicle at its thrust limit does not realise its command. A barrier settles a
    constant error d about d / k0 inside its surface (2 m/s^2 / 64 = 3 cm, the pair's whole vertical radius)
    and a transient goes further: with 1.5 (2 cm of margin for two Crazyflies) and 2, Crazyflies still
    collided in the swarm's crazyflie_stack flights (7 and 1 of its 250 under the linear law); with 2.5
    (6.4 cm; 12 cm for two paper quads, 0.40 m for an X500 over a paper quad) no vehicles collided in any of
    the swarm's flights. More costs the flights that fly safely: a bound above about 2.7 reaches the
    formations' ordinary flights (their baselines come to 2.7 to 3 times their ellipsoids), and 2.5 already
    holds back the flights a wrong model carries to 2.3 (a 2 % change of their mean error).
    max_margin 0.12 m: the paper quads' margin at 2.5, the most any pair keeps. What the margin holds is a
    model error of a few m/s^2 for tenths of a second, centimetres whatever the vehicles' size, while 2.5 times
    an X500's ellipsoid over a paper quad's is 0.24 m beyond it, and held the wrong model's flights in
    heavy_over_light 2 % from where they fly without the layer; capped, that pair keeps 1.75 times its ellipsoid.
    k0 64, k1 16 (a double pole at 8 rad/s, the time constant 0.125 s): the barrier acts once a pair closes
    faster than about l1 h (l1 the slower pole), so the faster the poles, the later and shorter it acts, and
    the smaller the displacement d / k0 of a model error; at 4 and 6 rad/s (inflation 2.5 to 3) it acted on
    formation5's clean flights (mean errors changed by 2.6 to 6 %), at 8 rad/s no more. The limits: the
    braking the barrier asks near its surface, about l1^2 h, stays within what the box gives a pair (7 m/s^2
    down, 3.6 to 10 up) for the h of a few centimetres where it acts; and 8 rad/s is well below what the loop
    carries (a control period of 20 ms, 0.16 rad of phase at 8 rad/s, the motors' 30 ms another 0.24).
    bandwidth 8 rad/s: `sim.observer.DEFAULT_BANDWIDTH`, chosen on the training flights for the observer that
    measures the same force from the same signals (a time constant of 0.125 s, as fast as the barrier's poles).
    ground_clearance 0.1 m and thrust_fraction 0.9: as before (the ground check is at 0.03 m; the rest of the
    thrust is the attitude's)."""

    inflation: float = 2.5  # -, the factor on each pair's collision ellipsoid that its barrier keeps out of
    max_margin: float = 0.12  # m, the most the barrier's surface lies beyond a pair's ellipsoid, vertically
    ground_clearance: float = 0.1  # m, the least height of a vehicle's centre
    k0: float = 64.0  # 1/s^2, the barrier's gain on h
    k1: float = 16.0  # 1/s, its gain on h' (>= 2 sqrt(k0): real poles)
    bandwidth: float = DEFAULT_BANDWIDTH  # rad/s, of the filter's own disturbance estimate (`sim.observer`'s)
    thrust_fraction: float = 0.9  # -, of a vehicle's full thrust the filter may command (the rest: the attitude's)

    def __post_init__(self) -> None:
        for name, unit, lo, hi, lo_open in _RANGES:
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Real):
                raise ConfigError(f"SafetyConfig.{name}: got {value!r}; allowed a number in {'(' if lo_open else '['}"
                                  f"{lo}, {hi}] {unit}")
            object.__setattr__(self, name, number(f"SafetyConfig.{name}", value, unit, lo, hi, lo_open=lo_open))
        if self.k1 * self.k1 < 4.0 * self.k0:
            raise ConfigError(f"SafetyConfig.k1: got {self.k1} with k0 = {self.k0}; allowed k1 >= 2 sqrt(k0) = "
                              f"{2.0 * math.sqrt(self.k0):.6g} 1/s (real poles: the barrier does not overshoot)")

    @property
    def poles(self) -> tuple[float, float]:
        """(l1, l2) 1/s, l1 <= l2: s^2 + k1 s + k0 = (s + l1)(s + l2)."""
        root = math.sqrt(max(self.k1 * self.k1 - 4.0 * self.k0, 0.0))
        return (self.k1 - root) / 2.0, (self.k1 + root) / 2.0

    def describe(self) -> dict[str, Any]:
        """Class, settings and method (JSON-serialisable), for logs and provenance."""
        return {"type": type(self).__name__, **asdict(self), "barrier": "h'' + k1 h' + k0 h >= 0",
                "pair": "h = sqrt((dx^2 + dy^2) / a^2 + dz^2 / c^2) - inflation, a, c: the pair's collision radii "
                        "(times (c + max_margin) / (inflation c) where (inflation - 1) c > max_margin)",
                "drift": "per barrier the more restrictive of f_hat and the filter's own estimate of the force felt",
                "solver": "dual active set (Goldfarb-Idnani), least squares on the commands", "tolerance": TOLERANCE}


def barrier_radii(config: SafetyConfig, radius_xy: Any, radius_z: Any) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's radii (V, V) m as the barrier h = q - inflation takes them: the collision radii, scaled by
    s = (c + max_margin) / (inflation c) where the margin (inflation - 1) c exceeds max_margin (beyond rounding),
    so that the barrier's surface lies max_margin beyond the ellipsoid vertically (and in proportion laterally);
    elsewhere the radii themselves, bit for bit. With a' = s a, c' = s c, h' = q / s - inflation is
    (q - s inflation) / s: the capped barrier times a constant, whose condition h'' + k1 h' + k0 h >= 0 is the
    same."""
    xy, z = (np.asarray(r, dtype=np.float64) for r in (radius_xy, radius_z))
    capped = (config.inflation - 1.0) * z > config.max_margin * (1.0 + 1e-9)
    scale = np.where(capped, (z + config.max_margin) / (config.inflation * np.where(capped, z, 1.0)), 1.0)
    return np.where(capped, xy * scale, xy), np.where(capped, z * scale, z)


def pack_params(config: SafetyConfig, radius_xy: Any, radius_z: Any, max_thrust: Any, dt: float = RATES.control_dt,
                max_tilt: float = math.radians(MAX_TILT_DEG),
                min_vertical: float = MIN_THRUST_G * GRAVITY) -> np.ndarray:
    """(N_PARAMS + 2 V V + V,) float64, as the compiled filter reads them: the scalars (N_PARAMS), then each pair's
    lateral and vertical barrier radii (V, V) m each (`barrier_radii` of the collision radii given), row by row,
    then each vehicle's full specific thrust max_thrust (V,) m/s^2 (its rotors' T/W g: `realised`); dt s, the
    period between the filter's calls (the estimate's measurement); max_tilt rad and min_vertical m/s^2, feedback
    linearisation's limits."""
    xy, z = (np.asarray(r, dtype=np.float64) for r in (radius_xy, radius_z))
    top = np.asarray(max_thrust, dtype=np.float64)
    if xy.ndim != 2 or xy.shape[0] != xy.shape[1] or z.shape != xy.shape or top.shape != xy.shape[:1]:
        raise ConfigError(f"safety: expected each pair's collision radii as two (V, V) arrays and each vehicle's "
                          f"thrust as (V,), got shapes {xy.shape}, {z.shape} and {top.shape}")
    off = ~np.eye(len(xy), dtype=bool)
    if not (np.isfinite(xy[off]).all() and np.isfinite(z[off]).all() and (xy[off] > 0).all() and (z[off] > 0).all()):
        raise ConfigError("safety: each pair's collision radii must be finite and > 0 m")
    xy, z = barrier_radii(config, xy, z)
    if not (isinstance(dt, numbers.Real) and math.isfinite(dt) and dt > 0):
        raise ConfigError(f"safety: dt: expected a finite number > 0 s, got {dt!r}")
    gain = 1.0 - math.exp(-config.bandwidth * float(dt))  # the estimate's step per tick (`sim.observer`'s filter)
    head = [config.inflation, config.ground_clearance, config.k0, config.k1, gain, float(dt), TOLERANCE, DEPENDENT,
            math.tan(max_tilt), float(min_vertical)]
    return np.concatenate([np.array(head, dtype=np.float64), xy.reshape(-1), z.reshape(-1), top])


def actuator_box(config: SafetyConfig, quads: Sequence[Any], max_tilt: float = math.radians(MAX_TILT_DEG),
                 min_vertical: float = MIN_THRUST_G * GRAVITY) -> tuple[np.ndarray, np.ndarray]:
    """(V, 3) lower and upper bounds (m/s^2, gravity excluded) of the commands the filter may give each
    vehicle: what feedback linearisation (`controllers.lqr.attitude_setpoint`, with these limits) realises.

    Vertical: from min_vertical - g (its floor, MIN_THRUST_G) to sqrt((c T/W g)^2 - a_lat^2) - g, where
    c = `thrust_fraction` and T/W the vehicle's thrust-to-weight (`quads[i].thrust_to_weight`).
    Lateral, each axis: |a| <= tan(max_tilt) min_vertical / sqrt(2), so that the lateral command stays in
    the tilt cone for every admissible vertical one, and the thrust within c T/W g.
    ConfigError when the box leaves a vehicle unable to hover (c too small for its T/W)."""
    lateral = math.tan(max_tilt) * min_vertical  # m/s^2, the lateral force the cone allows at the floor
    lower, upper = np.full((len(quads), 3), -lateral / math.sqrt(2.0)), np.full((len(quads), 3), lateral / math.sqrt(2.0))
    for i, q in enumerate(quads):
        most = config.thrust_fraction * q.thrust_to_weight * GRAVITY  # m/s^2, the specific thrust allowed
        if most * most - lateral * lateral <= GRAVITY * GRAVITY:
            need = math.sqrt(GRAVITY * GRAVITY + lateral * lateral) / (q.thrust_to_weight * GRAVITY)
            raise ConfigError(f"SafetyConfig.thrust_fraction: got {config.thrust_fraction}; vehicle {i} (thrust-to-"
                              f"weight {q.thrust_to_weight:.4g}) cannot hover within it: allowed ({need:.4g}, 1]")
        lower[i, 2], upper[i, 2] = min_vertical - GRAVITY, math.sqrt(most * most - lateral * lateral) - GRAVITY
    return lower, upper


# ----------------------------------------------------------------------------- the readable path


def _radii(params: np.ndarray, V: int) -> tuple[np.ndarray, np.ndarray]:
    """Each pair's lateral and vertical radii (V, V) from the packed params."""
    return (params[N_PARAMS:N_PARAMS + V * V].reshape(V, V),
            params[N_PARAMS + V * V:N_PARAMS + 2 * V * V].reshape(V, V))


def estimate_step(params: np.ndarray, vel: np.ndarray, state: np.ndarray) -> None:
    """The estimate's update at a call, in place on state (W, V, STATE_WIDTH), from vel (W, V, 3) the estimated
    velocities now: where a command was seen the tick before and the measurement is finite,
    d <- d + gain (d_meas - d), d_meas = (v - v_last) / dt - u_last (module doc). Readable; the kernel's bits."""
    gain, dt = params[4], params[5]
    d = state[..., 0:3]
    meas = (vel - state[..., 3:6]) / dt - state[..., 6:9]
    ok = (state[..., 9] != 0.0) & np.isfinite(meas).all(axis=-1)
    state[..., 0:3] = np.where(ok[..., None], d + gain * (meas - d), d)


def realised(params: np.ndarray, u: np.ndarray) -> np.ndarray:
    """(W, V, 3) m/s^2: the accelerations the commands u (W, V, 3) give, as feedback linearisation and the rotors
    realise them (`controllers.lqr.attitude_setpoint`'s limits, then the thrust): the vertical specific force at
    least min_vertical, the lateral within the tilt cone, the whole specific force at most the vehicle's full
    thrust (its direction kept: attitude first). The estimate measures the force felt against these, not against
    the commands: a saturated vehicle's shortfall is no disturbance, and counting it as one winds the estimate up
    (the filter, trusting it, asks ever more of the saturated vehicle). A command within the limits is returned as
    it is, bit for bit. Readable; the kernel's bits."""
    tan_tilt, floor = params[8], params[9]
    V = u.shape[-2]
    top = params[N_PARAMS + 2 * V * V:N_PARAMS + 2 * V * V + V]
    fz = u[..., 2] + GRAVITY
    low = fz < floor
    fx, fy, fz = u[..., 0], u[..., 1], np.where(low, floor, fz)
    nxy = np.sqrt(fx * fx + fy * fy)
    limit = tan_tilt * fz
    tilted = nxy > limit
    nxy = np.where(tilted, nxy, 1.0)
    fx, fy = np.where(tilted, fx * limit / nxy, fx), np.where(tilted, fy * limit / nxy, fy)
    t = np.sqrt(fx * fx + fy * fy + fz * fz)
    over = t > top
    scale = top / np.where(over, t, 1.0)
    fx, fy, fz = np.where(over, fx * scale, fx), np.where(over, fy * scale, fy), np.where(over, fz * scale, fz)
    out = np.stack([fx, fy, fz - GRAVITY], axis=-1)
    return np.where((low | tilted | over)[..., None], out, u)


def record_step(params: np.ndarray, vel: np.ndarray, u: np.ndarray, state: np.ndarray) -> None:
    """After a call: the velocities it saw and what the commands it let through realise (`realised`), for the next
    call's measurement."""
    state[..., 3:6], state[..., 6:9], state[..., 9] = vel, realised(params, u), 1.0


def constraint_rows(params: np.ndarray, lower: np.ndarray, upper: np.ndarray, pos: np.ndarray, vel: np.ndarray,
                    f_hat: np.ndarray, u: np.ndarray, estimate: np.ndarray | None = None
                    ) -> tuple[np.ndarray, np.ndarray]:
    """Every world's constraints A[w] x >= b[w] on its commands x = u[w].reshape(3 V): A (W, m, 3 V), b (W, m),
    m = P + 7 V for the P = V (V - 1) / 2 pairs. Rows: each pair i < j in turn (its ellipsoid); each vehicle's
    ground row; each command's lower and upper bound (the box widened to include u). A pair at one point has no
    row (zero, b = -inf). params: `SafetyFilter.params`; estimate (W, V, 3): the filter's d (None: zero)."""
    W, V = pos.shape[:2]
    I, J = np.triu_indices(V, 1)
    P, n = len(I), 3 * V
    inflation, zmin, k0, k1 = params[0], params[1], params[2], params[3]
    radius_xy, radius_z = _radii(params, V)
    d = np.zeros_like(f_hat) if estimate is None else estimate
    A, b = np.zeros((W, P + 7 * V, n)), np.full((W, P + 7 * V), -np.inf)
    dp, dv, df, dd = pos[:, I] - pos[:, J], vel[:, I] - vel[:, J], f_hat[:, I] - f_hat[:, J], d[:, I] - d[:, J]
    a2, c2 = radius_xy[I, J] * radius_xy[I, J], radius_z[I, J] * radius_z[I, J]  # (P,)
    # the pair's ellipsoid: q = sqrt(dp.M dp), M dp = (gx, gy, gz) = g n (module doc)
    gx, gy, gz = dp[..., 0] / a2, dp[..., 1] / a2, dp[..., 2] / c2
    q = np.sqrt(dp[..., 0] * gx + dp[..., 1] * gy + dp[..., 2] * gz)
    g = np.sqrt(gx * gx + gy * gy + gz * gz)
    apart = q > MIN_Q
    gs = np.where(apart, g, 1.0)
    nx, ny, nz = gx / gs, gy / gs, gz / gs
    qs = np.where(apart, q, 1.0)
    qd = (gx * dv[..., 0] + gy * dv[..., 1] + gz * dv[..., 2]) / qs
    bend = ((dv[..., 0] * dv[..., 0] + dv[..., 1] * dv[..., 1]) / a2 + dv[..., 2] * dv[..., 2] / c2 - qd * qd) / qs
    drift = np.minimum(nx * df[..., 0] + ny * df[..., 1] + nz * df[..., 2],
                       nx * dd[..., 0] + ny * dd[..., 1] + nz * dd[..., 2])
    for k, nk in enumerate((nx, ny, nz)):
        A[:, np.arange(P), 3 * I + k] = np.where(apart, nk, 0.0)
        A[:, np.arange(P), 3 * J + k] = np.where(apart, -nk, 0.0)
    b[:, :P] = np.where(apart, -(qs / gs) * (k1 * qd + k0 * (q - inflation) + bend) - drift, -np.inf)
    # ground: h = z - clearance
    ground = P + np.arange(V)
    A[:, ground, 3 * np.arange(V) + 2] = 1.0
    b[:, ground] = -np.minimum(f_hat[..., 2], d[..., 2]) - k1 * vel[..., 2] - k0 * (pos[..., 2] - zmin)
    # the box, widened to include the nominal command
    x, bound = u.reshape(W, n), P + V + 2 * np.arange(n)
    A[:, bound, np.arange(n)], A[:, bound + 1, np.arange(n)] = 1.0, -1.0
    b[:, bound] = np.minimum(lower.reshape(n), x)
    b[:, bound + 1] = -np.maximum(upper.reshape(n), x)
    return A, b


def solve_qp(A: np.ndarray, b: np.ndarray, u: np.ndarray, max_steps: int) -> tuple[np.ndarray, int]:
    """min |x - u|^2 s.t. A x >= b, one world (A (m, n), b (m,), u (n,)), by the dual active-set method of
    Goldfarb and Idnani (1983) with a unit Hessian: from x = u, add the most violated constraint p, moving
    x along z (a_p's part outside the active normals' span) and the active multipliers by -t r
    (a_p = N r + z); a multiplier reaching zero first drops its constraint (a partial step). Returns x and
    how many constraints were left unmet (one that cannot be met with those active: z = 0, no multiplier
    can fall). The readable form of `cbf_filter_kernel`'s solver (the same steps, in the same order)."""
    x = u.astype(np.float64, copy=True)
    active: list[int] = []
    lam = np.zeros(0)
    unmet = np.zeros(len(b), bool)
    steps = 0
    while steps < max_steps:
        slack = A @ x - b
        slack[active] = np.inf
        slack[unmet] = np.inf
        p = int(np.argmin(slack))  # (the first of equals, as the kernel)
        if not slack[p] < -TOLERANCE:
            break
        a, lam_p = A[p], 0.0
        while steps < max_steps:
            steps += 1
            N = A[active].T  # (n, q), the active normals
            try:
                r = np.linalg.solve(N.T @ N, N.T @ a) if active else np.zeros(0)
            except np.linalg.LinAlgError:
                unmet[p] = True
                break
            z = a - N @ r
            ratios = np.where(r > 0.0, lam / np.where(r > 0.0, r, 1.0), np.inf)
            drop = int(np.argmin(ratios)) if active else -1
            t1 = ratios[drop] if active else np.inf  # the step at which an active multiplier reaches zero
            zz = z @ z
            # the step that meets p (none when a_p lies in the active normals' span, or n of them are active already:
            # near-dependent normals, three pairs of a column, could otherwise pass the test by rounding)
            t2 = (b[p] - a @ x) / zz if zz > DEPENDENT * (a @ a) and len(active) < len(x) else np.inf
            t = min(t1, t2)
            if t == np.inf:  # p is infeasible with the active constraints
                unmet[p] = True
                break
            if t2 < np.inf:
                x = x + t * z
            lam, lam_p = lam - t * r, lam_p + t
            if t2 <= t1:
                active.append(p)
                lam = np.append(lam, lam_p)
                break
            del active[drop]
            lam = np.delete(lam, drop)
    return x, int(unmet.sum())


# ----------------------------------------------------------------------------- the filter


def safety_filter(config: SafetyConfig | None, vehicle_params: Any, controller: Any, n_worlds: int,
                  dt: float = RATES.control_dt, previous: SafetyFilter | None = None) -> SafetyFilter | None:
    """A simulator's filter for `config` (None: none; ConfigError for anything else) under `controller`'s feedback
    linearisation limits (its `max_tilt`, `min_vertical` where it has them, else the LQR's defaults), for the
    scene's vehicles and each pair's collision ellipsoid (`vehicle_params`: `quads`, `collision_xy`,
    `collision_z`, `sim.vehicle_params.VehicleParams`), n_worlds worlds called every dt s. `previous` (the
    filter this one replaces when the simulator binds again): its estimates carry over where the shape agrees."""
    if config is None:
        return None
    tilt = getattr(controller, "max_tilt", math.radians(MAX_TILT_DEG))
    floor = getattr(controller, "min_vertical", MIN_THRUST_G * GRAVITY)
    out = SafetyFilter(config, vehicle_params.quads, vehicle_params.collision_xy, vehicle_params.collision_z, tilt,
                       floor, dt=dt, n_worlds=n_worlds)
    if isinstance(previous, SafetyFilter) and previous.state.shape == out.state.shape:
        out.state[:] = previous.state
    return out


class SafetyFilter:
    """The CBF filter for a scene's vehicles (`quads`, each with its `thrust_to_weight`) and each pair's collision
    ellipsoid (radius_xy, radius_z (V, V) m: `sim.vehicle_params.collision_radii`), under a feedback linearisation
    with limits `max_tilt` (rad) and `min_vertical` (m/s^2) (`actuator_box`), called every dt s on n_worlds
    worlds: `state` (n_worlds, V, STATE_WIDTH) holds each world's and vehicle's estimate (module doc)."""

    def __init__(self, config: SafetyConfig, quads: Sequence[Any], radius_xy: Any, radius_z: Any,
                 max_tilt: float = math.radians(MAX_TILT_DEG), min_vertical: float = MIN_THRUST_G * GRAVITY, *,
                 dt: float = RATES.control_dt, n_worlds: int = 1):
        if not isinstance(config, SafetyConfig):
            raise ConfigError(f"safety: expected a sim.safety.SafetyConfig or None, got {type(config).__name__}")
        self.config = config
        self.max_tilt, self.min_vertical = float(max_tilt), float(min_vertical)
        self.lower, self.upper = actuator_box(config, quads, self.max_tilt, self.min_vertical)
        V = len(quads)
        if np.shape(radius_xy) != (V, V) or np.shape(radius_z) != (V, V):
            raise ConfigError(f"safety: expected each pair's collision radii as ({V}, {V}) arrays for {V} vehicles, "
                              f"got {np.shape(radius_xy)} and {np.shape(radius_z)}")
        self.params = pack_params(config, radius_xy, radius_z, [q.thrust_to_weight * GRAVITY for q in quads], dt,
                                  self.max_tilt, self.min_vertical)
        self.state = np.zeros((int(n_worlds), V, STATE_WIDTH))

    def reset(self, worlds: Any = None) -> None:
        """These worlds (None: all) start afresh: no estimate, nothing measured (the simulator's reset calls it)."""
        self.state[slice(None) if worlds is None else np.asarray(worlds, dtype=np.int64)] = 0.0

    @property
    def address(self) -> int:
        """The address of the compiled filter's C function (`safety_function`), for the fused tick."""
        return int(safety_function().address)

    def filter_into(self, pos: np.ndarray, vel: np.ndarray, f_hat: np.ndarray, u: np.ndarray,
                    state: np.ndarray | None = None) -> tuple[int, int]:
        """The compiled filter on u (W, V, 3) float64 in place, its estimate in `state` (W, V, STATE_WIDTH), updated
        (None: the filter's own, `self.state`, of the simulator's worlds); returns (worlds changed, barriers left
        unmet)."""
        state = self.state if state is None else state
        if state.shape != (*u.shape[:2], STATE_WIDTH):
            raise ConfigError(f"safety: the estimate's state has shape {state.shape}, the commands {u.shape}")
        counts = np.zeros(2, np.int64)
        cbf_filter_kernel(self.params, self.lower, self.upper, pos, vel, f_hat, u, counts, state)
        return int(counts[0]), int(counts[1])

    def __call__(self, pos: np.ndarray, vel: np.ndarray, u: np.ndarray, f_hat: np.ndarray | None = None,
                 state: np.ndarray | None = None) -> np.ndarray:
        """The filtered commands (W, V, 3) m/s^2, compiled (a fresh array); state (W, V, STATE_WIDTH) the estimate's,
        updated in place (None: a fresh one, nothing measured: the estimate is zero)."""
        out = np.array(u, dtype=np.float64, order="C")
        pos, vel = (np.ascontiguousarray(a, dtype=np.float64) for a in (pos, vel))
        f_hat = np.zeros_like(out) if f_hat is None else np.ascontiguousarray(f_hat, dtype=np.float64)
        self.filter_into(pos, vel, f_hat, out, np.zeros((*out.shape[:2], STATE_WIDTH)) if state is None else state)
        return out

    def reference(self, pos: np.ndarray, vel: np.ndarray, u: np.ndarray, f_hat: np.ndarray | None = None,
                  state: np.ndarray | None = None) -> tuple[np.ndarray, int]:
        """The filtered commands (W, V, 3) and the barriers left unmet, in NumPy (the readable form); state as for
        a call (updated in place as the compiled filter updates it)."""
        u = np.asarray(u, dtype=np.float64)
        W, V = u.shape[:2]
        f_hat = np.zeros_like(u) if f_hat is None else np.asarray(f_hat, dtype=np.float64)
        state = np.zeros((W, V, STATE_WIDTH)) if state is None else state
        vel = np.asarray(vel, float)
        estimate_step(self.params, vel, state)
        A, b = constraint_rows(self.params, self.lower, self.upper, np.asarray(pos, float), vel, f_hat, u,
                               state[..., 0:3])
        x = u.reshape(W, 3 * V)
        out, unmet = u.copy(), 0
        violated = np.flatnonzero(((A @ x[..., None])[..., 0] - b < -TOLERANCE).any(axis=1))
        for w in violated:  # one QP per world: its pairs couple its vehicles
            solved, missed = solve_qp(A[w], b[w], x[w], MAX_STEPS * sum(A[w].shape))
            solved = np.minimum(np.maximum(solved.reshape(V, 3), np.minimum(self.lower, u[w])),
                                np.maximum(self.upper, u[w]))  # into the widened box, as the kernel
            out[w], unmet = solved, unmet + missed
        record_step(self.params, vel, out, state)
        return out, unmet

    def apply(self, controller: Any, state: Any, ref: Any, f_hat: np.ndarray, out: Any, lookahead: float) -> int:
        """The simulator's step after `controller.command_setpoint(state, ref, f_hat, out, ...)`: filter out.acc
        (the `controllers.lqr.Setpoint` buffers) and redo feedback linearisation where it acted; returns the
        worlds changed. A `FeedbackLinearisedLQR` (stateless) runs its own step again with the filtered command as
        the override, as the fused tick does; any other controller gets `attitude_setpoint` on the changed
        vehicles, towards the heading of its own set-point. The estimate is the filter's own (`self.state`)."""
        exact = type(controller) is FeedbackLinearisedLQR
        nominal = None if exact else out.acc.copy()
        changed, _ = self.filter_into(state.pos, state.vel, f_hat, out.acc)
        if not changed:
            return 0
        if exact:
            controller.command_setpoint(state, ref, f_hat, out, None, out.acc, lookahead)
            return changed
        moved = (out.acc != nominal).any(axis=-1)  # (W, V)
        rot = out.rot[moved]  # the heading c1 in span(b1, b3) with no vertical part: b1 - (b1_z / b3_z) b3
        heading = rot[:, :, 0] - (rot[:, 2, 0] / rot[:, 2, 2])[:, None] * rot[:, :, 2]
        thrust, rot_des = attitude_setpoint(out.acc[moved], np.arctan2(heading[:, 1], heading[:, 0]), self.max_tilt,
                                            self.min_vertical)
        out.thrust[moved], out.rot[moved] = thrust, rot_des
        return changed
