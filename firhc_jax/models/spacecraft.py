"""Rigid spacecraft attitude control with three pairs of on/off thrusters: 27 torque patterns.

Notation and units (SI unless said):

* ``x`` ``[6]`` = ``[sigma, omega]``: ``sigma`` ``[3]`` the modified Rodrigues
  parameters (MRP) of the body frame relative to the target frame
  (dimensionless; a rotation by ``phi`` about a unit axis ``e`` is
  ``sigma = e tan(phi / 4)``, so ``4 sigma`` is nearly the rotation vector in rad
  for small angles), ``omega`` ``[3]`` the body rates (rad/s) in body axes.
* ``u`` ``[3]`` in {-1, 0, +1}^3 (``CONTROLS`` ``[27, 3]``, ``fj.product_controls``):
  the thruster pair of each body axis fires one way, the other, or not; the
  torque is ``tau = max_torque * u`` (N m), held over one sample ``ts`` (s).
* ``p``: the parameters of one loop (and one step), a dict: ``p["inertia"]``
  ``[3]`` principal moments of inertia J1, J2, J3 (kg m^2, body axes are the
  principal axes), ``p["fuel"]`` ``[]`` the weight of one firing thruster pair
  per sample (deg^2, the cost's unit). ``FIRHC.simulate`` takes them with a
  leading axis ``steps`` (``step_params``), a batch of loops with ``[B, steps]``.

Equations: the MRP kinematics and Euler's rotation equations

    d sigma / dt = 1/4 [(1 - sigma.sigma) I + 2 [sigma]x + 2 sigma sigma^T] omega
    J d omega / dt = tau - omega x (J omega),

integrated over each sample by classical RK4 sub-steps (the model
``make_problem(..., substeps=2)``, the plant ``SpacecraftParams.plant_substeps``:
the plant is the finer integration of the same equations), then switched to the shadow set
``-sigma / |sigma|^2`` when ``|sigma| > 1`` (rotations past 180 deg), which
describes the same attitude.

Stage cost (deg^2, >= 0) of the step that reached ``x_next`` with ``u``:

    |(4 sigma_next) in deg|^2 + rate_weight |omega_next in deg/s|^2 + p["fuel"] * (thruster pairs firing),

the pointing error, the rate and the fuel of the step.
"""
from __future__ import annotations

import dataclasses
import math

import jax
import jax.numpy as jnp
import numpy as np

from .. import Problem, product_controls

CONTROLS = product_controls([-1.0, 0.0, 1.0], repeat=3)  # [27, 3] torque direction per axis
DEG = 180.0 / math.pi  # deg per rad


@dataclasses.dataclass(frozen=True)
class SpacecraftParams:
    """Actuators, sampling and the nominal body (a small satellite; our choice)."""

    max_torque: float = 0.05  # N m, torque of one firing thruster pair
    ts: float = 2.0  # s, sampling period (torque held over it)
    plant_substeps: int = 8  # RK4 sub-steps per sample in the plant
    inertia: tuple = (12.0, 10.0, 8.0)  # kg m^2, nominal principal moments (``random_loops`` spreads them)


PARAMS = SpacecraftParams()
RATE_WEIGHT = 10.0  # s^2: a rate of 1 deg/s costs as much as a pointing error of 3.2 deg


def _rates(sigma, omega, torque, inertia):
    """``(d sigma / dt, d omega / dt)`` of the MRP kinematics and Euler's equations."""
    s2 = sigma @ sigma
    d_sigma = 0.25 * ((1.0 - s2) * omega + 2.0 * jnp.cross(sigma, omega) + 2.0 * (sigma @ omega) * sigma)
    d_omega = (torque - jnp.cross(omega, inertia * omega)) / inertia
    return d_sigma, d_omega


def _integrator(params: SpacecraftParams, substeps: int):
    """``f(x, u, p) -> x_next``: one sample of ``substeps`` RK4 steps, then the shadow set switch."""
    h = params.ts / substeps

    def f(x, u, p):
        inertia = jnp.asarray(p["inertia"], x.dtype)
        torque = params.max_torque * u.astype(x.dtype)

        def substep(_, s):
            sigma, omega = s
            a = _rates(sigma, omega, torque, inertia)
            b = _rates(sigma + 0.5 * h * a[0], omega + 0.5 * h * a[1], torque, inertia)
            c = _rates(sigma + 0.5 * h * b[0], omega + 0.5 * h * b[1], torque, inertia)
            d = _rates(sigma + h * c[0], omega + h * c[1], torque, inertia)
            return (sigma + (h / 6.0) * (a[0] + 2.0 * b[0] + 2.0 * c[0] + d[0]),
                    omega + (h / 6.0) * (a[1] + 2.0 * b[1] + 2.0 * c[1] + d[1]))

        # A loop, not unrolled: unrolled under the search's vmaps XLA may recompute the chain per consumer.
        sigma, omega = jax.lax.fori_loop(0, substeps, substep, (x[:3], x[3:]))
        s2 = sigma @ sigma
        sigma = jnp.where(s2 > 1.0, -sigma / s2, sigma)
        return jnp.concatenate([sigma, omega])

    return f


def make_plant(params: SpacecraftParams = PARAMS):
    """``plant(x, u, p) -> x_next``: the spacecraft after one sample (``plant_substeps`` RK4 steps)."""
    return _integrator(params, params.plant_substeps)


def make_problem(horizon: int, params: SpacecraftParams = PARAMS, rate_weight: float = RATE_WEIGHT,
                 substeps: int = 2) -> Problem:
    """The attitude controller: the module's stage cost over ``horizon`` samples, no terminal set.

    ``rate_weight`` (s^2) weighs the squared rate against the squared pointing error; ``substeps``: RK4
    sub-steps per sample of the prediction model. The callables take the per-loop ``p`` (module
    docstring): solve with ``params=`` always. Each call makes new callables (a new compilation): build
    the problem once per run.
    """
    if not rate_weight >= 0:
        raise ValueError(f"rate_weight must be >= 0 s^2, got {rate_weight}")
    if isinstance(substeps, bool) or not isinstance(substeps, (int, np.integer)) or substeps < 1:
        raise ValueError(f"substeps must be an int >= 1, got {substeps!r}")
    dynamics = _integrator(params, int(substeps))

    def stage_cost(x_next, u, p):
        e = (4.0 * DEG) * x_next[:3]  # [3] deg, the pointing error
        w = DEG * x_next[3:]  # [3] deg/s
        firing = jnp.sum(jnp.abs(u)).astype(x_next.dtype)
        return e @ e + rate_weight * (w @ w) + jnp.asarray(p["fuel"], x_next.dtype) * firing

    return Problem(dynamics, CONTROLS, stage_cost, horizon)


def step_params(inertia, fuel, steps: int) -> dict:
    """Per-step params of loops: ``inertia`` ``[..., 3]`` (kg m^2) and ``fuel`` ``[...]`` (deg^2) held
    over ``steps`` samples, as ``{"inertia": [..., steps, 3], "fuel": [..., steps]}`` (NumPy)."""
    inertia, fuel = np.asarray(inertia, float), np.asarray(fuel, float)
    lead = fuel.shape
    if inertia.shape != lead + (3,):
        raise ValueError(f"inertia must be [..., 3] with fuel's leading axes {lead}, got shape {inertia.shape}")
    return {"inertia": np.broadcast_to(inertia[..., None, :], lead + (steps, 3)).copy(),
            "fuel": np.broadcast_to(fuel[..., None], lead + (steps,)).copy()}


def random_loops(count: int, rng: np.random.Generator, params: SpacecraftParams = PARAMS,
                 max_angle: float = 20.0, max_rate: float = 0.5, spread: float = 0.2) -> tuple[np.ndarray, np.ndarray]:
    """``(x0 [count, 6], inertia [count, 3])``: a random attitude error of at most ``max_angle`` deg about
    a random axis, body rates uniform within ``max_rate`` deg/s per axis, and each principal moment
    within ``spread`` (relative) of ``params.inertia``."""
    axis = rng.normal(size=(count, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angle = np.radians(rng.uniform(0.0, max_angle, (count, 1)))
    sigma = axis * np.tan(angle / 4.0)
    omega = np.radians(rng.uniform(-max_rate, max_rate, (count, 3)))
    inertia = np.asarray(params.inertia) * rng.uniform(1.0 - spread, 1.0 + spread, (count, 3))
    return np.concatenate([sigma, omega], axis=1), inertia


def pointing_error(x) -> np.ndarray:
    """Rotation angle (deg) of the attitude in ``x`` ``[..., 6]`` from the target: ``4 atan |sigma|``."""
    return 4.0 * DEG * np.arctan(np.linalg.norm(np.asarray(x)[..., :3], axis=-1))


def dcm(sigma) -> np.ndarray:
    """``[..., 3, 3]`` direction cosine matrix (target frame to body frame) of the MRP ``sigma`` ``[..., 3]``."""
    s = np.asarray(sigma, float)
    s2 = np.sum(s * s, axis=-1)[..., None, None]
    cross = np.zeros(s.shape[:-1] + (3, 3))
    cross[..., 0, 1], cross[..., 0, 2], cross[..., 1, 2] = -s[..., 2], s[..., 1], -s[..., 0]
    cross = cross - np.swapaxes(cross, -1, -2)
    return np.eye(3) + (8.0 * cross @ cross - 4.0 * (1.0 - s2) * cross) / (1.0 + s2) ** 2


def angular_momentum(x, inertia) -> np.ndarray:
    """``[..., 3]`` the angular momentum (N m s) in the target (inertial) frame: ``C(sigma)^T J omega``,
    conserved without torque."""
    x = np.asarray(x, float)
    h_body = np.asarray(inertia, float) * x[..., 3:]
    return np.einsum("...ji,...j->...i", dcm(x[..., :3]), h_body)
