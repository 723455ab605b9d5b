"""The one source of every physical and timing parameter, with units.

`assets/quad.xml` carries the same numbers (MJCF has no imports); a test compiles
the scene and checks it against this module, so the two cannot drift apart.
Controller and estimator settings live with their components (`controllers.lqr.LQRConfig`,
`sim.estimation.MocapConfig`, `sim.turbulence.OUTurbulence`); this module holds the
vehicle, the rates and the experiments' geometry.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

__all__ = ["GRAVITY", "LEADER_POSITION", "SEPARATION_RANGE", "QUAD", "RATES", "QuadParams", "Rates"]

GRAVITY = 9.81  # m/s^2, magnitude; MuJoCo's world z is up, gravity along -z
LEADER_POSITION = (0.0, 0.0, 2.5)  # m, world frame: where Alpha hovers in the experiments (paper: 2.5 m up)
SEPARATION_RANGE = (0.3, 2.0)  # m, allowed vertical separations: closer collides, farther leaves little wake


@dataclass(frozen=True)
class QuadParams:
    """One quadrotor (paper section 5.C): ~0.7 kg, 0.26 m longest diagonal."""

    mass: float = 0.70  # kg, whole vehicle (body + arms + rotors)
    inertia: tuple[float, float, float] = (2.5e-3, 2.5e-3, 4.5e-3)  # kg m^2, body frame diagonal
    arm_length: float = 0.09  # m, body centre to each rotor axis
    rotor_radius: float = 0.04  # m, collision/visual only
    thrust_to_weight: float = 2.3  # -, all four rotors at full thrust over weight
    motor_time_constant: float = 0.03  # s, first-order lag from commanded to actual thrust
    yaw_moment_coeff: float = 0.016  # m, rotor drag torque per newton of thrust

    @property
    def weight(self) -> float:
        """Vehicle weight (N)."""
        return self.mass * GRAVITY

    @property
    def max_rotor_thrust(self) -> float:
        """Thrust limit of one rotor (N)."""
        return self.thrust_to_weight * self.weight / 4.0

    @property
    def hover_rotor_thrust(self) -> float:
        """Thrust of one rotor in a level hover (N)."""
        return self.weight / 4.0

    @property
    def rotor_positions(self) -> np.ndarray:
        """(4, 3) m, rotor centres in the body frame, X configuration.

        Order matches the MJCF actuators rotor0..rotor3: front-left, back-left,
        back-right, front-right (x forward, y left, z up).
        """
        c = self.arm_length / np.sqrt(2.0)
        return np.array([[c, c, 0.0], [-c, c, 0.0], [-c, -c, 0.0], [c, -c, 0.0]])

    @property
    def rotor_spin(self) -> np.ndarray:
        """(4,) sign of each rotor's reaction torque about body z (+1: counter-clockwise torque)."""
        return np.array([1.0, -1.0, 1.0, -1.0])

    @property
    def diagonal(self) -> float:
        """Longest body diagonal, rotor tip to rotor tip (m)."""
        return 2.0 * (self.arm_length + self.rotor_radius)


@dataclass(frozen=True)
class Rates:
    """Loop rates. Everything runs on the autopilot grid (a fixed divisor of physics).

    physics 500 Hz; autopilot, field and motion capture 100 Hz; controller 50 Hz;
    learned model 45 Hz, which is not a multiple of the controller rate: the latest
    prediction is held, as on the paper's vehicles.
    """

    physics_dt: float = 0.002  # s (500 Hz)
    physics_per_autopilot: int = 5  # -> autopilot, field and mocap at 100 Hz
    autopilot_per_control: int = 2  # -> controller at 50 Hz
    predictor_hz: float = 45.0  # Hz, evaluated at the first autopilot tick after each 1/45 s

    @property
    def autopilot_dt(self) -> float:
        return self.physics_dt * self.physics_per_autopilot

    @property
    def control_dt(self) -> float:
        return self.autopilot_dt * self.autopilot_per_control

    @property
    def physics_per_control(self) -> int:
        return self.physics_per_autopilot * self.autopilot_per_control


QUAD = QuadParams()
RATES = Rates()
