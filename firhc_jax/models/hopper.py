"""Pneumatic vertical hopping robot (the paper's Sec. III and IV.1): plant, prediction model, and the FIRHC
problem on valve b.

A vertical double-acting cylinder: the body M rides on the piston, the foot m
is the cylinder end that touches the ground. Chamber a pushes the body up,
chamber b (rod side) pulls it down. Each chamber has one on/off three-way
valve, command ``+1`` supply, ``0`` closed, ``-1`` exhaust to atmosphere.

Coordinates (m, positive up): ``x`` body, ``y`` foot (``y < 0`` is ground
penetration), both zero in the static stance with the piston at mid-stroke.
``s = x - y`` is the piston's stroke from mid-position; the chamber volumes are
``V_a = V_mida + A_a s`` and ``V_b = V_midb - A_b s``.

Plant state ``[6]``: ``[x, xdot, y, ydot, P_a, P_b]`` (m, m/s, m, m/s, Pa, Pa;
pressures absolute). Motion eqs. (21)-(22) with viscous seal friction, ground
eq. (23), adiabatic pressure eqs. (13)-(14), orifice flow eq. (15).

Prediction model state ``[5]``: ``[x, xdot, P_a, P_b, airborne]``, the
loss-free contact model of eqs. (7), (13)-(15) with the foot on the ground
(``y = 0``, so ``x`` is the stroke), frozen once the foot would lift off. It is
what the controller predicts with; friction is absent on purpose (the
controller must hold the energy despite it, as in the paper).

All functions are elementwise arithmetic (no matmuls), so a search gives the
same bits for the same sequence whatever its batch size.

Controller (last section: the problem and the pieces of its closed loop; the ``FIRHC`` itself is built by
``firhc_jax.apps.hopper.controller``; ``docs/applications/hopper.md`` explains and measures it):

* Control period 5 ms: longer than the 2-5 ms switching time of fast 3/2
  solenoid valves, so a commanded state is actually reached within a period,
  and short against the 0.2 s stance (about 40 decisions per stance).
* In contact (foot on the ground at the sample): side a by the paper's on/off
  law, side b by FIRHC over the three valve states. In flight both valves are
  sealed; the valve drivers are gated by the foot contact at every plant step
  (``control_period``), so they close at lift-off, not at the next sample.
* FIRHC, cost (24): ``(E - E_d)^2 + 0.1 (xdot - xdot_d)^2 + 10 u^2`` per
  step, ``u`` in {-0.01, 0, 0.01} (exhaust, closed, supply), terminal
  constraint ``|E(k+N) - E_d| <= 0.02 J``, prediction by ``model_step``, which
  stops at a predicted lift-off. Two deviations from the paper:

  - ``E_d`` is eq. (20) evaluated for the air now in the chambers
    (``orbit_energy``), not a constant: E is ~96% stored air energy, and a
    constant target lets the controller replace the friction losses with air,
    which parks the robot standing with E = E_d (one hop, then none).
  - eq. (19) is applied to the centre of mass: the foot leaves at rest, so the
    body must leave with ``(M + m) / M * g T_air / 2`` for a flight of T_air.

* Fallback: when no sequence meets the terminal constraint the same search
  runs without it (counted as an infeasible step). Should even that find
  nothing (it has not happened), valve b stays closed (the controller's
  ``u_safe``) and the step is counted as unsolved.

The closed loop's pieces: ``observe`` maps the plant state ``[6]`` to the
model's ``[5]``, ``actuate`` adds side a's law and seals the valves in flight,
and ``make_plant`` integrates one period.
"""
from __future__ import annotations

import dataclasses
import functools
import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from scipy.optimize import brentq

import firhc_jax as fj

PSI = 6894.757  # Pa per psi


@dataclasses.dataclass(frozen=True)
class HopperParams:
    """Plant parameters, SI units (pressures absolute).

    Sources: masses, friction and ground from the paper (Sec. IV.1); gas data
    and supply pressure from the issue; the actuator is ours because the
    paper's ref. [4] is not available: an ISO 6432 mini cylinder (bore 12 mm,
    rod 6 mm, standard stroke 160 mm) with external dead volumes, and valve
    flow constants from Richer & Hurmuzlu (2000), ASME JDSMC 122(3):416-425.

    Design rule for the free choices (see ``docs/applications/hopper.md``): the nominal
    pressure of chamber a is the geometric mean of atmosphere and supply (equal
    pressure ratios for charging and exhausting); chamber b's follows from the
    static force balance; the dead volumes make the stance stiffness of the two
    air springs equal ``M (pi / T_2)^2`` for the specified gait (T_hop = 0.4 s,
    T_air = 0.2 s, so T_2 = 0.1615 s, eq. 17), with the quadratic terms of the
    two springs cancelling so the stance oscillation is as harmonic as eqs.
    (17)-(18) assume. ``stance_stiffness`` checks the first condition. The
    orifice is sized so that exhausting b near the bottom of the stance can
    replace the ~0.3 J the seal friction takes per stance (about 12 mg of air
    per stance at a few tens of ms of opening).
    """

    M: float = 0.54  # kg, body on the piston (paper)
    m: float = 0.05  # kg, foot (paper)
    b: float = 2.0  # N s/m, viscous seal friction (paper eqs. 21-22)
    k_ground: float = 1.0e6  # N/m, ground stiffness (paper eq. 23)
    b_ground: float = 1000.0  # N s/m, ground damping (paper eq. 23)
    g: float = 9.81  # m/s^2
    gamma: float = 1.4  # -, ratio of specific heats of air
    R: float = 287.0  # J/(kg K), gas constant of air
    T: float = 293.0  # K, air and flow temperature
    P_atm: float = 101325.0  # Pa
    P_supply: float = 101325.0 + 80.0 * PSI  # Pa, 80 psi gauge (paper)
    bore: float = 0.012  # m, piston diameter (ISO 6432)
    rod: float = 0.006  # m, rod diameter (ISO 6432 for a 12 mm bore)
    stroke: float = 0.160  # m, full stroke, mid-position at s = 0 (ISO 6432 standard stroke)
    V_dead_a: float = 31.3e-6  # m^3, dead volume of chamber a incl. tubing and reservoir (design rule)
    V_dead_b: float = 18.7e-6  # m^3, dead volume of chamber b incl. tubing and reservoir (design rule)
    orifice: float = 2.0e-3  # m, valve orifice diameter (3/2 solenoid valve; sized for the friction losses, see docs)
    C_f: float = 0.25  # -, discharge coefficient (Richer & Hurmuzlu order of magnitude)
    P_a0: float = 2.5e5  # Pa, static stance pressure of chamber a (design rule)

    # -- derived geometry ------------------------------------------------------
    @property
    def A_a(self) -> float:
        """m^2, piston area (chamber a)."""
        return math.pi * self.bore**2 / 4

    @property
    def A_r(self) -> float:
        """m^2, rod area A_a - A_b."""
        return math.pi * self.rod**2 / 4

    @property
    def A_b(self) -> float:
        """m^2, annulus area (chamber b)."""
        return self.A_a - self.A_r

    @property
    def A_v(self) -> float:
        """m^2, valve orifice area."""
        return math.pi * self.orifice**2 / 4

    @property
    def V_mida(self) -> float:
        """m^3, chamber a volume at mid-stroke."""
        return self.V_dead_a + self.A_a * self.stroke / 2

    @property
    def V_midb(self) -> float:
        """m^3, chamber b volume at mid-stroke."""
        return self.V_dead_b + self.A_b * self.stroke / 2

    @property
    def P_b0(self) -> float:
        """Pa, static stance pressure of chamber b: P_a0 A_a - P_b0 A_b - P_atm A_r = M g."""
        return (self.P_a0 * self.A_a - self.P_atm * self.A_r - self.M * self.g) / self.A_b

    # -- orifice constants (Richer & Hurmuzlu 2000) ------------------------------
    @property
    def C1(self) -> float:
        """sqrt(kg K/J), choked flow constant (0.040418 for air)."""
        g = self.gamma
        return math.sqrt(g / self.R * (2 / (g + 1)) ** ((g + 1) / (g - 1)))

    @property
    def C2(self) -> float:
        """sqrt(kg K/J), subsonic flow constant (0.156174 for air)."""
        return math.sqrt(2 * self.gamma / (self.R * (self.gamma - 1)))

    @property
    def P_crit(self) -> float:
        """-, critical pressure ratio (0.528 for air)."""
        g = self.gamma
        return (2 / (g + 1)) ** (g / (g - 1))

    def stance_stiffness(self) -> float:
        """N/m, stiffness of the two air springs at the static stance (closed chambers)."""
        g = self.gamma
        return g * self.P_a0 * self.A_a**2 / self.V_mida + g * self.P_b0 * self.A_b**2 / self.V_midb


class Gait(NamedTuple):
    """The desired gait of Sec. III.2."""

    T_hop: float  # s, hopping period (specified)
    T_air: float  # s, flight time (specified)
    T2: float  # s, compression period, eq. (17)
    x_t1: float  # m, body position at lift-off, eq. (18)
    xdot_t1: float  # m/s, body velocity at lift-off, eq. (19)
    E_d: float  # J, desired energy, eq. (20)


# ---------------------------------------------------------------------------
# Thermodynamics
# ---------------------------------------------------------------------------

def power(x, a):
    """``x ** a`` for positive ``x`` and a constant float exponent, as ``exp(a log x)``.

    XLA:CPU evaluates a float power element by element through a scalar library
    call, exp and log as vector code; the prediction model evaluates about 80
    powers per control period and node (measured in docs/dev/xla_notes.md). Agrees
    with ``**`` to about 1e-14 relative.
    """
    return jnp.exp(a * jnp.log(x))


def orifice_flow(p_up, p_down, p: HopperParams):
    """Mass flow (kg/s) through a valve orifice from ``p_up`` to ``p_down``, eq. (15).

    Standard form (Richer & Hurmuzlu): choked, ``C_f A_v C1 P_u / sqrt(T)``,
    when ``P_d / P_u <= 0.528``; subsonic, ``C_f A_v C2 P_u / sqrt(T) r^(1/k)
    sqrt(1 - r^((k-1)/k))`` with ``r = P_d / P_u``, above it. The paper's text
    labels the two cases the other way round and prints C1 in both; this is the
    physics (the two branches meet at the critical ratio). Flow reverses when
    ``p_down > p_up`` (negative result).
    """
    hi, lo = jnp.maximum(p_up, p_down), jnp.minimum(p_up, p_down)
    r = lo / hi
    k = p.gamma
    subsonic = p.C2 * power(r, 1 / k) * jnp.sqrt(jnp.maximum(1 - power(r, (k - 1) / k), 0.0))
    shape = jnp.where(r <= p.P_crit, p.C1, subsonic)
    return jnp.sign(p_up - p_down) * p.C_f * p.A_v * hi / math.sqrt(p.T) * shape


def valve_flow(cmd, P, p: HopperParams):
    """Mass flow (kg/s) into a chamber at pressure ``P`` for valve ``cmd`` (+1 supply, 0 closed, -1 exhaust)."""
    source = jnp.where(cmd > 0, p.P_supply, p.P_atm)
    return jnp.where(cmd == 0, 0.0, orifice_flow(source, P, p))


def chamber_volumes(s, p: HopperParams):
    """Chamber volumes (m^3) at stroke ``s``: ``V_a = V_mida + A_a s``, ``V_b = V_midb - A_b s``."""
    return p.V_mida + p.A_a * s, p.V_midb - p.A_b * s


def pressure_rates(s, sdot, Pa, Pb, mdot_a, mdot_b, p: HopperParams):
    """Adiabatic chamber pressure rates (Pa/s), eqs. (13)-(14), flow at temperature T."""
    Va, Vb = chamber_volumes(s, p)
    k = p.gamma
    dPa = k * p.R * p.T / Va * mdot_a - k * Pa * (p.A_a * sdot) / Va
    dPb = k * p.R * p.T / Vb * mdot_b + k * Pb * (p.A_b * sdot) / Vb
    return dPa, dPb


def piston_force(Pa, Pb, p: HopperParams):
    """Net pneumatic force (N) pushing the body up and the foot down: P_a A_a - P_b A_b - P_atm A_r."""
    return Pa * p.A_a - Pb * p.A_b - p.P_atm * p.A_r


def chamber_energy(P, V, p: HopperParams):
    """PE of one chamber, eq. (6): ``P V / (1 - k) ((P / P_atm)^((1 - k) / k) - 1)`` (J)."""
    k = p.gamma
    return P * V / (1 - k) * (power(P / p.P_atm, (1 - k) / k) - 1)


def energy(x, xdot, Pa, Pb, p: HopperParams):
    """Total conservative energy in contact, eq. (6) (J); ``x`` is the stroke (foot on the ground)."""
    Va, Vb = chamber_volumes(x, p)
    return (0.5 * p.M * xdot**2 + chamber_energy(Pa, Va, p) + chamber_energy(Pb, Vb, p)
            + p.P_atm * p.A_r * x + p.M * p.g * x)


def nominal_pressures(s, p: HopperParams):
    """Pressures (Pa) at stroke ``s`` with the static charge of air, sealed: the adiabats through (P_a0, P_b0)."""
    Va, Vb = chamber_volumes(s, p)
    k = p.gamma
    return p.P_a0 * power(p.V_mida / Va, k), p.P_b0 * power(p.V_midb / Vb, k)


def nominal_potential(x, p: HopperParams):
    """Potential part of eq. (6) (J) at stroke ``x`` with the static charge of air."""
    Pa, Pb = nominal_pressures(x, p)
    return energy(x, 0.0, Pa, Pb, p)


# ---------------------------------------------------------------------------
# Plant: eqs. (13)-(15), (21)-(23)
# ---------------------------------------------------------------------------

def plant_rhs(state, cmd, p: HopperParams):
    """Time derivative of the plant state ``[6]`` for valve commands ``cmd`` ``[2]`` (a, b).

    The ground force (23) acts only while ``y < 0`` and is clipped at zero: the
    ground pushes, it never pulls the foot back during lift-off.
    """
    x, xd, y, yd, Pa, Pb = state[0], state[1], state[2], state[3], state[4], state[5]
    s, sd = x - y, xd - yd
    F = piston_force(Pa, Pb, p)
    friction = p.b * sd  # on the body; the opposite on the foot
    ground = jnp.where(y < 0, jnp.maximum(-p.k_ground * y - p.b_ground * yd, 0.0), 0.0)
    xdd = (F - friction) / p.M - p.g
    ydd = (-F + friction + ground) / p.m - p.g
    dPa, dPb = pressure_rates(s, sd, Pa, Pb, valve_flow(cmd[0], Pa, p), valve_flow(cmd[1], Pb, p), p)
    return jnp.stack([xd, xdd, yd, ydd, dPa, dPb])


def rk4(f, state, dt):
    """One classical Runge-Kutta step of ``state' = f(state)``."""
    k1 = f(state)
    k2 = f(state + 0.5 * dt * k1)
    k3 = f(state + 0.5 * dt * k2)
    k4 = f(state + dt * k3)
    return state + dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)


def plant_step(state, cmd, p: HopperParams, dt: float):
    """Advance the plant ``[6]`` by ``dt`` with commands ``[2]`` held (RK4)."""
    return rk4(lambda z: plant_rhs(z, cmd, p), state, dt)


def simulate_open_loop(state0, cmd, p: HopperParams, dt: float, steps: int):
    """Integrate ``steps`` fixed steps with commands ``[2]`` held; returns the states ``[steps + 1, 6]``."""
    def body(z, _):
        z = plant_step(z, cmd, p, dt)
        return z, z

    _, traj = jax.lax.scan(body, state0, None, length=steps)
    return jnp.concatenate([state0[None], traj])


def plant_energy(state, p: HopperParams):
    """Mechanical + pneumatic energy of the plant (J), conserved without valves, friction and ground damping.

    Eq. (6) with the stroke ``x - y`` in the chamber and rod terms, plus the
    foot's kinetic and gravitational energy and the ground spring; in contact
    with the foot at rest it reduces to eq. (6).
    """
    x, xd, y, yd, Pa, Pb = (state[..., i] for i in range(6))
    s = x - y
    Va, Vb = chamber_volumes(s, p)
    return (0.5 * p.M * xd**2 + 0.5 * p.m * yd**2 + chamber_energy(Pa, Va, p) + chamber_energy(Pb, Vb, p)
            + p.P_atm * p.A_r * s + p.M * p.g * x + p.m * p.g * y
            + jnp.where(y < 0, 0.5 * p.k_ground * y**2, 0.0))


# ---------------------------------------------------------------------------
# Prediction model: eqs. (7), (13)-(15) in contact, no friction
# ---------------------------------------------------------------------------

def model_rhs(w, cmd, p: HopperParams):
    """Derivative of ``[x, xdot, P_a, P_b]`` ``[4]`` with the foot on the ground, eqs. (7), (13)-(15)."""
    x, xd, Pa, Pb = w[0], w[1], w[2], w[3]
    xdd = piston_force(Pa, Pb, p) / p.M - p.g
    dPa, dPb = pressure_rates(x, xd, Pa, Pb, valve_flow(cmd[0], Pa, p), valve_flow(cmd[1], Pb, p), p)
    return jnp.stack([xd, xdd, dPa, dPb])


def model_step(z, cmd, p: HopperParams, period: float, substeps: int):
    """Advance the prediction state ``[5]`` by one control period (``substeps`` RK4 steps, commands held).

    The foot leaves the ground when the ground reaction of eq. (8) with
    ``ydd = 0``, ``P_a A_a - P_b A_b - P_atm A_r + m g``, turns negative; from
    then on the state is frozen (``z[4] = 1``): valves are sealed in flight and
    the controller acts only in contact, so the prediction ends at lift-off and
    the remaining stages keep charging the lift-off state. Without this the
    model would not see that charging b right after touch-down pulls the foot
    off the ground again.
    """
    dt = period / substeps
    f = lambda w: model_rhs(w, cmd, p)  # noqa: E731

    def substep(_, z):
        w = rk4(f, z[:4], dt)
        lifted = piston_force(w[2], w[3], p) + p.m * p.g < 0
        airborne = z[4] > 0
        return jnp.concatenate([jnp.where(airborne, z[:4], w), jnp.where(airborne | lifted, 1.0, 0.0)[None]])

    return jax.lax.fori_loop(0, substeps, substep, z)


def model_energy(z, p: HopperParams):
    """Eq. (6) of a prediction state ``[..., >= 4]`` (J)."""
    return energy(z[..., 0], z[..., 1], z[..., 2], z[..., 3], p)


def liftoff_stroke(Ca, Cb, p: HopperParams, iterations: int = 6):
    """Stroke (m) where the foot leaves the ground, ``P_a A_a - P_b A_b - P_atm A_r = -m g``,
    for sealed chambers with adiabatic constants ``Ca = P_a V_a^k``, ``Cb = P_b V_b^k``.

    Newton's method from eq. (18)'s linear estimate for the static charge; the
    force is smooth and monotone in the stroke, so a few iterations reach
    round-off.
    """
    k = p.gamma

    def newton(_, x):
        Va, Vb = chamber_volumes(x, p)
        Pa, Pb = Ca / power(Va, k), Cb / power(Vb, k)
        residual = piston_force(Pa, Pb, p) + p.m * p.g
        slope = -k * (Pa * p.A_a**2 / Va + Pb * p.A_b**2 / Vb)
        return x - residual / slope

    x0 = jnp.zeros_like(Ca) + (p.M + p.m) * p.g / p.stance_stiffness()  # like Ca
    return jax.lax.fori_loop(0, iterations, newton, x0)


def orbit_energy(z, v_liftoff: float, p: HopperParams):
    """Eq. (20) for the air now in the chambers of ``z`` ``[..., >= 4]`` (J).

    The energy of the loss-free orbit that leaves the ground with body
    velocity ``v_liftoff`` at the lift-off stroke (eq. 18's condition) of the
    current air charge. For the static charge it is eq. (20)'s E_d (up to the
    linearisation in eq. 18); unlike a constant E_d it does not move when air
    is added or removed, so it measures the gait energy, not the stored air.
    """
    k = p.gamma
    Va, Vb = chamber_volumes(z[..., 0], p)
    Ca, Cb = z[..., 2] * power(Va, k), z[..., 3] * power(Vb, k)
    x1 = liftoff_stroke(Ca, Cb, p)
    Va1, Vb1 = chamber_volumes(x1, p)
    return energy(x1, v_liftoff, Ca / power(Va1, k), Cb / power(Vb1, k), p)


# ---------------------------------------------------------------------------
# Static states and the desired energy (Sec. III.2)
# ---------------------------------------------------------------------------

def flight_stroke(p: HopperParams) -> float:
    """Stroke (m) at which the sealed springs exert no force: where the body rests relative to the foot in flight."""
    def force(s):
        Pa, Pb = nominal_pressures(s, p)
        return float(piston_force(Pa, Pb, p))

    half = p.stroke / 2
    return brentq(force, -half, half, xtol=1e-15)


def static_state(p: HopperParams) -> np.ndarray:
    """Plant state ``[6]`` standing still on the ground, valves closed: mid-stroke, foot pressed in by (M + m) g."""
    y = -(p.M + p.m) * p.g / p.k_ground
    return np.array([y, 0.0, y, 0.0, p.P_a0, p.P_b0])


def apex_state(p: HopperParams, height: float) -> np.ndarray:
    """Plant state ``[6]`` at rest in the air, foot at ``height``, springs at their flight equilibrium."""
    s = flight_stroke(p)
    Pa, Pb = nominal_pressures(s, p)
    return np.array([height + s, 0.0, height, 0.0, float(Pa), float(Pb)])


def solve_T2(T_hop: float, T_air: float, M: float, m: float, g: float) -> float:
    """Compression period T_2 (s) from eq. (17), by Brent's method."""
    if not (0 < T_air < T_hop):
        raise ValueError(f"need 0 < T_air < T_hop, got T_air={T_air}, T_hop={T_hop}")

    def residual(T2):
        w2 = (math.pi / T2) ** 2
        arg = 8 * (M + m) * g / (8 * (M + m) * g + M * w2 * g * T_air**2)
        return 2 * T2 / math.pi * math.asin(arg) + T_air + T2 - T_hop

    return brentq(residual, 1e-9, T_hop - T_air, xtol=1e-14)


def desired_energy(T_hop: float, T_air: float, params: HopperParams) -> Gait:
    """Desired gait and energy (Sec. III.2): T_2 by eq. (17), x(t1) by (18), xdot(t1) by (19), E_d by (20).

    The chamber terms of eq. (20) are taken on the adiabats of the static charge
    (``nominal_pressures``): the loss-free orbit the energy describes.
    """
    p = params
    T2 = solve_T2(T_hop, T_air, p.M, p.m, p.g)
    x1 = (p.M + p.m) * p.g / (p.M * (math.pi / T2) ** 2)
    v1 = T_air * p.g / 2
    Pa, Pb = nominal_pressures(x1, p)
    E_d = float(energy(x1, v1, Pa, Pb, p))
    return Gait(T_hop, T_air, T2, x1, v1, E_d)


# ---------------------------------------------------------------------------
# FIRHC on valve b (Sec. IV.1): problem, bound, the closed loop's pieces, sampled plant
# ---------------------------------------------------------------------------

T_HOP, T_AIR = 0.4, 0.2  # s, gait specification (paper)
CONTROL_PERIOD = 0.005  # s, see the module docstring
PLANT_DT = 5e-5  # s, fixed RK4 step of the plant (ground contact eigenvalue ~ -1.9e4 1/s)
MODEL_SUBSTEPS = 5  # RK4 steps per control period in the prediction model (1 ms)
LAMBDA1, LAMBDA2, BETA = 1.0, 0.1, 10.0  # weights of cost (24)
VALVE_B = (-0.01, 0.0, 0.01)  # u: exhaust, closed, supply (the paper's scaling)
ENERGY_TOL = 0.02  # J, terminal constraint |E(k+N) - E_d| <= tol
A_DEADBAND = 0.01  # relative: side a charges below (1 - 1%) of the reference pressure
SUBSTEPS = int(round(CONTROL_PERIOD / PLANT_DT))  # plant steps per control period
IN_FLIGHT = 2.0  # model state's airborne flag for a decision taken in flight (see ``make_problem``)
OPEN_COST = BETA * min(u * u for u in VALVE_B if u != 0)  # cost of one period with valve b open (0.001)
PASSIVE_DRIFT = 1e-6  # J, allowance per closed period for the RK4 drift of the conserved E - E_d (seen: <= 1e-10)
A_IDLE_MARGIN = 1e-6  # relative margin on side a's threshold for "its law never fires below this node"


def side_a_law(s, Pa, p: HopperParams):
    """Paper's on/off law for side a in contact: charge (1.0) if ``P_a < P_a0 (V_mida / V_a)^gamma``, else 0.0.

    ``s`` is the stroke (the paper's x in contact). A 1% dead band (sensor
    resolution) keeps round-off on the adiabat from firing a 5 ms charge; the
    plant has no leaks, so with it the law stays idle unless air is lost.
    """
    Pa_ref = nominal_pressures(s, p)[0]
    return jnp.where(Pa < (1 - A_DEADBAND) * Pa_ref, 1.0, 0.0)


def liftoff_velocity(p: HopperParams) -> float:
    """Body lift-off velocity targeted (m/s): eq. (19) for the centre of mass (module docstring)."""
    return (p.M + p.m) / p.M * desired_energy(T_HOP, T_AIR, p).xdot_t1


def static_target(p: HopperParams) -> float:
    """The controller's E_d (J) for the static charge of air."""
    return float(orbit_energy(np.array([0.0, 0.0, p.P_a0, p.P_b0]), liftoff_velocity(p), p))


def make_problem(horizon: int, params: HopperParams = HopperParams(), bound: bool = False,
                 terminal: bool = True) -> fj.Problem:
    """The FIRHC problem for valve b (built once per arguments, so its search compiles once).

    Prediction state ``[5]``: ``[x, xdot, P_a, P_b, airborne]`` (see
    ``model_step``; ``airborne`` 1 from a predicted lift-off on). Input
    ``u`` ``[1]``: one of ``VALVE_B``. The model applies side a's law itself,
    so the prediction sees what the plant gets. ``airborne = IN_FLIGHT``
    (set by ``observe``) marks a decision taken in flight: the valves are
    sealed, so the state stays put, only the valve term ``10 u^2`` is charged
    and the terminal constraint holds; the optimum is valve b closed, found in
    3N nodes. Contact decisions are unaffected (bit for bit).

    ``bound``: add the lower bound of ``docs/guide/bounds.md`` (energy-band
    reachability and energy-error cost), exact results with fewer nodes.
    ``terminal=False``: without the terminal set, for the fallback search; with
    ``bound`` its bound is the same one without the ``+inf`` that only the
    terminal set justifies (the core drops a bound with the terminal set).
    """
    if terminal:
        return _problems(params, horizon)["bounded" if bound else "plain"]
    return _problems(params, horizon)["relaxed" if bound else "open"]


@functools.lru_cache(maxsize=None)
def _problems(params: HopperParams, horizon: int) -> dict:
    p = params
    v_liftoff, E_target = liftoff_velocity(p), static_target(p)

    def dynamics(z, u):
        cmd = jnp.stack([side_a_law(z[0], z[2], p), jnp.sign(u[0])])
        return jnp.where(z[4] == IN_FLIGHT, z, model_step(z, cmd, p, CONTROL_PERIOD, MODEL_SUBSTEPS))

    def energy_error(z):  # E_d re-evaluated for the air in the chambers of z (deviation 1)
        return model_energy(z, p) - orbit_energy(z, v_liftoff, p)

    def stage_cost(z, u):
        x, xd = z[0], z[1]
        # Desired velocity from the loss-free energy balance on the static charge's orbit.
        v2 = 2 * (E_target - nominal_potential(x, p)) / p.M
        xd_d = jnp.sign(xd) * jnp.sqrt(jnp.maximum(v2, 0.0))
        gait = LAMBDA1 * energy_error(z) ** 2 + LAMBDA2 * (xd - xd_d) ** 2
        return jnp.where(z[4] == IN_FLIGHT, 0.0, gait) + BETA * u[0] ** 2

    def terminal(z):
        return (z[4] == IN_FLIGHT) | (jnp.abs(energy_error(z)) <= ENERGY_TOL)

    def bound(z, steps_left, band: bool):
        """docs/guide/bounds.md. In flight 0. After a predicted lift-off (frozen state) the exact cost with valve b
        closed. In contact, with side a's law provably idle, e stays put while valve b is closed: either b stays
        closed (every stage costs at least LAMBDA1 e^2) or it opens at least once (BETA u^2 = OPEN_COST); with side
        a possibly charging, 0. ``band``: the terminal set applies, so a frozen or closed-valve future with e
        outside the band is infeasible (+inf)."""
        e, s = jnp.abs(energy_error(z)), steps_left.astype(z.dtype)
        frozen = s * stage_cost(z, jnp.zeros(1, z.dtype))
        j = jnp.arange(1, horizon + 1, dtype=z.dtype)
        drift = jnp.where(j <= s, jnp.maximum(e - j * PASSIVE_DRIFT, 0.0), 0.0)  # e after j closed periods
        closed = LAMBDA1 * jnp.sum(drift * drift)
        airborne = z[4] == 1.0
        if band:
            closed = jnp.where(e - s * PASSIVE_DRIFT <= ENERGY_TOL, closed, jnp.inf)
            frozen = jnp.where(e <= ENERGY_TOL, frozen, jnp.inf)
        Pa_ref = nominal_pressures(z[0], p)[0]
        a_idle = z[2] >= (1 - A_DEADBAND) * (1 + A_IDLE_MARGIN) * Pa_ref  # side_a_law with a margin: never fires
        value = jnp.where(airborne, frozen, jnp.where(a_idle, jnp.minimum(closed, OPEN_COST), 0.0))
        return jnp.where(z[4] == IN_FLIGHT, 0.0, (1 - 1e-9) * value)  # margin for the search's own rounding

    def lower_bound(z, steps_left):
        return bound(z, steps_left, True)

    def relaxed_bound(z, steps_left):
        return bound(z, steps_left, False)

    plain = fj.Problem(dynamics, jnp.asarray(VALVE_B), stage_cost, horizon, terminal)
    return dict(plain=plain, bounded=plain.replace(lower_bound=lower_bound), open=plain.replace(terminal=None),
                relaxed=plain.replace(terminal=None, lower_bound=relaxed_bound))


def initial_state(p: HopperParams) -> np.ndarray:
    """Plant state ``[6]`` of the closed loop's start: at rest at the apex of the specified flight (foot at
    ``g T_air^2 / 8``)."""
    return apex_state(p, p.g * T_AIR**2 / 8)


def contact(X):
    """Foot on the ground (plant states ``[..., 6]``)."""
    return X[..., 2] <= 0


def observe(X, u_prev):
    """Prediction state ``[5]`` from a plant state ``[6]``: stroke, stroke rate, pressures, and ``IN_FLIGHT``
    when the foot is off the ground (0 on it)."""
    flag = jnp.where(contact(X), 0.0, IN_FLIGHT)
    return jnp.stack([X[0] - X[2], X[1] - X[3], X[4], X[5], flag])


def actuate(X, u, p: HopperParams):
    """The plant's commands ``[2]`` (a, b) in {-1, 0, 1} for the searched input ``u`` ``[1]``: side a by
    ``side_a_law``, valve b by ``u``, both 0 (sealed) when the foot is off the ground at the sample."""
    return jnp.where(contact(X), jnp.stack([side_a_law(X[0] - X[2], X[4], p), jnp.sign(u[0])]), 0.0)


def control_period(X, cmd, p: HopperParams):
    """One control period of the plant from ``X`` ``[6]`` with commands ``cmd`` ``[2]``:
    ``(X_end, [SUBSTEPS, 6] states after each plant step)``.

    The valve drivers are gated by foot contact at every plant step, so the
    valves close at lift-off, not at the next sample.
    """
    def step(X, _):
        X = plant_step(X, cmd * contact(X), p, PLANT_DT)
        return X, X

    return jax.lax.scan(step, X, None, length=SUBSTEPS)


@functools.lru_cache(maxsize=None)
def make_plant(params: HopperParams = HopperParams()):
    """``plant(X, cmd) -> X`` one control period later, for ``FIRHC.simulate`` (jitted, cached)."""
    return jax.jit(lambda X, cmd: control_period(X, cmd, params)[0])
