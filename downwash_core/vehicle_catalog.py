"""The built-in vehicle kinds, each number with its source: the paper quad, the Crazyflie 2.1, the
Neural-Swarm data set's large Crazyflie and PX4's X500.

Each is a `downwash_core.vehicle_kind.VehicleKind` whose `source` cites every number (one line per
number after a summary line) and whose `estimated` names the numbers that are estimates.
`downwash_core.vehicles` registers them in `VEHICLES` (and re-exports them); the table of kinds
is in its docstring. Units: SI (kg, m, N, s).
"""

from __future__ import annotations

import math

from downwash_core.params import GRAVITY, QUAD
from downwash_core.vehicle_kind import ThrustMap, VehicleKind

__all__ = ["PAPER_QUAD", "CRAZYFLIE_2_1", "CRAZYFLIE_LARGE", "X500"]

PAPER_QUAD = VehicleKind.from_params(
    "paper_quad", QUAD,
    description="the paper's custom quadrotor (Alpha and Bravo), the testbed's default",
    estimated=("inertia", "arm_length", "rotor_radius", "thrust_to_weight", "motor_time_constant", "yaw_moment_coeff"),
    source="""Smith et al. 2023 (arXiv 2305.18983) sec. 5.C, as downwash_core.params.QUAD
mass 0.70 kg: paper sec. 5.C ("weigh ~0.7 kg (including batteries)")
arm_length 0.09 m: paper sec. 5.C's 0.26 m longest body diagonal = 2 (arm + rotor radius), with the chosen radius
inertia, rotor_radius, thrust_to_weight, motor_time_constant, yaw_moment_coeff: the testbed's choices
  (downwash_core.params.QuadParams, assets/quad.xml), not given in the paper; rotor_radius 0.04 m is a
  collision/visual size, smaller than the real vehicle's propellers (docs/fields.md)""",
)

_NEURAL_SWARM = "Neural-Swarm data set (github.com/aerorobotics/neural-swarm), data/training/"

# utiasDSL/drone-models release 0.1.0 (commit 77f04ab13efbee1179322c9e22119e1d964113bd, MIT),
# the parameters the crazyflow simulator validates against. Configuration cf2x_L250.
_CF_L = 0.03253  # m, drone-models `L`: per-axis moment arm (the mixing matrix is +-1 on x and y)
_CF_THRUST_MAX = 0.12  # N per motor, drone-models `thrust_max`
_CF_MASS = 0.0319  # kg, drone-models `mass`

CRAZYFLIE_2_1 = VehicleKind(
    name="crazyflie_2_1",
    mass=_CF_MASS,
    inertia=(16.8e-6, 16.8e-6, 29.8e-6),
    arm_length=_CF_L * math.sqrt(2.0),  # 0.0460 m: centre to motor (Bitcraze: 92 mm motor to motor)
    rotor_radius=23.55e-3,
    thrust_to_weight=4.0 * _CF_THRUST_MAX / (_CF_MASS * GRAVITY),  # so that max_rotor_thrust is 0.12 N
    motor_time_constant=0.0858607,
    yaw_moment_coeff=0.007350862856566459,
    description="Bitcraze Crazyflie 2.1, brushed motors, stock propellers, 250 mAh battery (drone-models cf2x_L250)",
    estimated=("inertia", "rotor_radius"),
    thrust_map=ThrustMap(11.093358483549203, -39.08104165843915, -9.525647087583181, 20.573302305476638,
                         38.42885066644033, source=_NEURAL_SWARM + "datacollection19_12_11_2019/defaultcf.txt "
                         "(C_00 ... C_11, fit score 0.998): an unmodified Crazyflie 2.1"),
    source="""utiasDSL/drone-models 0.1.0 (commit 77f04ab, MIT), drone_models/data/params.toml [cf2x_L250]
mass 0.0319 kg: params.toml [cf2x_L250] mass
arm_length 0.0460 m: params.toml L = 0.03253 m is the per-axis moment arm (mixing matrix +-1 on x and y), x sqrt(2)
inertia (16.8, 16.8, 29.8) e-6 kg m^2: params.toml J (marked TODO there); Foerster 2015, "System
  Identification of the Crazyflie 2.0 Nano Quadrocopter" (BSc thesis, ETH Zurich) identified
  (16.57, 16.66, 29.26) e-6 on a 0.027 kg vehicle, within 2 %
rotor_radius 0.02355 m: params.toml prop_radius (marked "TODO check" there)
thrust_to_weight 1.53: params.toml thrust_max = 0.12 N per motor, 4 x 0.12 N / (0.0319 kg g)
motor_time_constant 0.0859 s: drone_models/so_rpy_rotor/params.toml [cf2x_L250] thrust_time_coef (fitted
  first-order lag of the collective thrust, rotor_vel_dot = (cmd - rotor_vel) / thrust_time_coef)
yaw_moment_coeff 0.00735 m: params.toml thrust2torque (Foerster 2015: 0.005964552)
thrust_map: the Neural-Swarm data set's system identification of an unmodified Crazyflie 2.1""",
)

# The Neural-Swarm data set's "large" vehicle: a Crazyflie 2.1 on a larger (Parrot) frame with its
# propellers. The data set gives its mass, its ground clearance and its thrust map; the geometry is
# estimated (the data set states none): larger propellers on a frame that clears them.
_LARGE_MAP = ThrustMap(44.10386631845999, -122.51151800146272, -36.18484254283743, 53.10772568607133,
                       107.6819263349139, source=_NEURAL_SWARM + "datacollection19_12_11_2019/parrot_frame.txt "
                       "(C_00 ... C_11, fit score 0.995): the large frame")
_LARGE_MASS = 0.067  # kg, parrot_frame.txt ("mass: 67g")
_LARGE_MAX_ROTOR_THRUST = float(_LARGE_MAP.thrust(65535.0, 4.2)[0])  # N, full PWM on a full battery
_CF_ARM = _CF_L * math.sqrt(2.0)
_LARGE_ARM, _LARGE_ROTOR = 0.06, 0.033  # m, estimated

CRAZYFLIE_LARGE = VehicleKind(
    name="crazyflie_large",
    mass=_LARGE_MASS,
    # the Crazyflie's inertia scaled as m l^2 (the same mass distribution on a larger frame)
    inertia=tuple(i * (_LARGE_MASS / _CF_MASS) * (_LARGE_ARM / _CF_ARM) ** 2 for i in (16.8e-6, 16.8e-6, 29.8e-6)),
    arm_length=_LARGE_ARM,
    rotor_radius=_LARGE_ROTOR,
    thrust_to_weight=4.0 * _LARGE_MAX_ROTOR_THRUST / (_LARGE_MASS * GRAVITY),
    motor_time_constant=-0.01 / math.log(1.0 - 0.16),  # 0.057 s
    yaw_moment_coeff=0.007350862856566459,
    description="Crazyflie 2.1 on a larger (Parrot) frame and propellers: the Neural-Swarm data set's large vehicle",
    estimated=("inertia", "arm_length", "rotor_radius", "motor_time_constant", "yaw_moment_coeff"),
    thrust_map=_LARGE_MAP,
    source="""Neural-Swarm data set (Shi et al., github.com/aerorobotics/neural-swarm, data/training), vehicles cf100-cf102
mass 0.067 kg: data/training/datacollection19_12_11_2019/parrot_frame.txt ("mass: 67g")
thrust_to_weight: its thrust map at full PWM and 4.2 V (4 rotors), over the weight
thrust_map: parrot_frame.txt (C_00 ... C_11)
arm_length 0.06 m, rotor_radius 0.033 m: estimated (the data set states no geometry): a larger propeller
  than the Crazyflie's 23.5 mm, on a frame whose rotors do not overlap
inertia: estimated, crazyflie_2_1's scaled by mass x arm length^2
motor_time_constant 0.057 s: estimated from the data set's training code, which lags the thrust by a
  first-order filter of 0.16 per 10 ms step (learning/utils.py), -0.01 s / ln(0.84)
yaw_moment_coeff: estimated, crazyflie_2_1's""",
)


def _x500_whole_vehicle() -> tuple[float, tuple[float, float, float]]:
    """Mass (kg) and inertia diagonal (kg m^2) of PX4's x500: base_link plus the four rotor links.

    From PX4/PX4-gazebo-models models/x500_base/model.sdf: base_link 2.0 kg, inertia
    (0.021667, 0.021667, 0.04) at its origin; rotors 0.016077 kg each at (+-0.174, +-0.174,
    0.06) m with ixx 3.846e-7, iyy 2.612e-5, izz 2.650e-5 (a blade along x): averaged over
    a turn ((ixx + iyy) / 2 in the plane), moved to the combined centre of mass (parallel axes).
    """
    m_b, i_b = 2.0, (0.02166666666666667, 0.02166666666666667, 0.04000000000000001)
    m_r, xy, z = 0.016076923076923075, 0.174, 0.06
    i_r_plane, i_r_z = (3.8464910483993325e-07 + 2.6115851691700804e-05) / 2.0, 2.649858234714004e-05
    mass = m_b + 4.0 * m_r
    z_c = 4.0 * m_r * z / mass  # the centre of mass lies above base_link's origin
    d_b2 = z_c**2
    d_r_lat2, d_r_z2 = xy**2, (z - z_c) ** 2
    ixx = i_b[0] + m_b * d_b2 + 4.0 * (i_r_plane + m_r * (d_r_lat2 + d_r_z2))
    iyy = i_b[1] + m_b * d_b2 + 4.0 * (i_r_plane + m_r * (d_r_lat2 + d_r_z2))
    izz = i_b[2] + 4.0 * (i_r_z + m_r * 2.0 * d_r_lat2)
    return mass, (ixx, iyy, izz)


_X500_MASS, _X500_INERTIA = _x500_whole_vehicle()
_X500_MAX_ROTOR_THRUST = 8.54858e-06 * 1000.0**2  # N: motorConstant x maxRotVelocity^2

X500 = VehicleKind(
    name="x500",
    mass=_X500_MASS,
    inertia=_X500_INERTIA,
    arm_length=0.174 * math.sqrt(2.0),  # 0.246 m (a 500 mm wheelbase frame)
    rotor_radius=0.2792307692307692 / 2.0,  # 0.1396 m: the rotor collision box (an 11 inch propeller)
    thrust_to_weight=4.0 * _X500_MAX_ROTOR_THRUST / (_X500_MASS * GRAVITY),
    motor_time_constant=(0.0125 + 0.025) / 2.0,
    yaw_moment_coeff=0.016,
    description="Holybro X500, 2 kg class (PX4's Gazebo x500 model)",
    estimated=("inertia", "motor_time_constant"),
    source="""PX4/PX4-gazebo-models (BSD-3-Clause) models/x500_base/model.sdf and models/x500/model.sdf
files as of commits 008216e (x500_base/model.sdf) and 0f0e45d (x500/model.sdf)
mass 2.064 kg: base_link 2.0 kg + 4 rotor links x 0.016077 kg (x500_base/model.sdf)
arm_length 0.246 m: rotor links at (+-0.174, +-0.174) m, x sqrt(2) (x500_base/model.sdf)
inertia (0.0239, 0.0239, 0.0440) kg m^2: estimated, base_link's (0.02167, 0.02167, 0.04) plus the rotor links by
  parallel axes, rotor inertia averaged over a turn (x500_base/model.sdf)
rotor_radius 0.1396 m: half the rotor collision box, 0.27923 m (x500_base/model.sdf; an 11 inch propeller)
thrust_to_weight 1.69: motorConstant 8.54858e-6 N s^2 x maxRotVelocity (1000 rad/s)^2 = 8.549 N per rotor
  (x500/model.sdf, gz MulticopterMotorModel)
motor_time_constant 0.01875 s: estimated, the mean of timeConstantUp 0.0125 s and timeConstantDown 0.025 s
  (x500/model.sdf); one symmetric lag here
yaw_moment_coeff 0.016 m: momentConstant (x500/model.sdf)""",
)
