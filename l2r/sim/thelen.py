"""Thelen 2003 muscles as OpenSim 4.6 computes them, integrated beside MuJoCo's physics step.

Each muscle has two states, as in OpenSim: activation `a`, first-order in the excitation with
time constants that scale with activation, and fibre length `lce`, whose rate follows from the
equilibrium of fibre and series-elastic tendon (OpenSim's `Thelen2003Muscle`: the tendon force
fixes the fibre force, and the inverted force-velocity curve gives the fibre speed). The tendon
force, a function of `lce` and the muscle-tendon length L alone, pulls on the MuJoCo tendon.

Integration, per physics step of `dt` with the excitation held and L moving at its current
speed:
- activation is advanced exactly (the ODE separates for a constant excitation);
- fibre length by backward Euler on `substeps` sub-steps: its time constant drops below a
  millisecond at low activation, where any explicit step of MuJoCo's size diverges;
- `stiffness` returns dF/dL of the step's end force, so that the env can hand MuJoCo's implicit
  integrator the tendon's stiffness as damping over the step (a stiff Achilles tendon at full
  activation would otherwise ring the light foot at the edge of the step's stability).
"""

from __future__ import annotations

import math

import numba
import numpy as np

from l2r.sim.opensim import Muscle

# OpenSim 4.6's values for the Thelen2003Muscle properties the .osim file leaves at default.
AF = 0.25  # force-velocity shape
FLEN = 1.4  # maximum normalised eccentric force
KSHAPE_ACTIVE = 0.45  # active force-length width
FV_EXTRAPOLATION = 0.95  # fraction of the eccentric asymptote beyond which the curve is linear
MIN_ACTIVATION = 0.01
MAX_PENNATION = math.acos(0.1)
DEFAULT_ACTIVATION = 0.05  # what OpenSim's muscles start at (`default_activation`)
TOE_FORCE, TOE_SHAPE = 0.33, 3.0  # tendon curve: normalised force and shape at the toe's end

# Columns of the parameter table, one row per muscle.
(MAX_FORCE, OPTIMAL_LENGTH, SLACK_LENGTH, WIDTH, MAX_SPEED, TAU_ACTIVATION, TAU_DEACTIVATION,
 TOE_STRAIN, TENDON_SLOPE, MUSCLE_STRAIN, PASSIVE_SHAPE, PASSIVE_SCALE, MIN_FIBER_LENGTH) = range(13)  # fmt: skip
NUM_PARAMS = 13


def muscle_parameters(muscles: list[Muscle]) -> np.ndarray:
    """The kernels' parameter table (n, NUM_PARAMS) for .osim muscles, derived values included."""
    table = np.zeros((len(muscles), NUM_PARAMS))
    e3 = math.exp(3.0)
    for row, m in zip(table, muscles):
        width = m.optimal_length * math.sin(m.pennation)
        toe_strain = 99.0 * m.tendon_strain * e3 / (166.0 * e3 - 67.0)  # Thelen's 0.609 e0, exactly
        row[MAX_FORCE] = m.max_force
        row[OPTIMAL_LENGTH] = m.optimal_length
        row[SLACK_LENGTH] = m.slack_length
        row[WIDTH] = width
        row[MAX_SPEED] = m.max_velocity * m.optimal_length
        row[TAU_ACTIVATION] = m.activation_tau
        row[TAU_DEACTIVATION] = m.deactivation_tau
        row[TOE_STRAIN] = toe_strain
        row[TENDON_SLOPE] = (1.0 - TOE_FORCE) / (m.tendon_strain - toe_strain)
        row[MUSCLE_STRAIN] = m.muscle_strain
        row[PASSIVE_SHAPE] = m.passive_shape
        row[PASSIVE_SCALE] = math.exp(m.passive_shape) - 1.0  # an exp the passive curve saves on every call
        # OpenSim's fixed-width pennation model: no shorter than 1 % of optimal, nor than the
        # length at which the fibre would reach the maximum pennation angle
        row[MIN_FIBER_LENGTH] = max(0.01 * m.optimal_length, width / math.sin(MAX_PENNATION))
    return table


@numba.njit(cache=True, error_model="numpy")
def _tendon_force(strain: float, p: np.ndarray) -> float:
    """Normalised tendon force: exponential toe, then linear."""
    if strain > p[TOE_STRAIN]:
        return p[TENDON_SLOPE] * (strain - p[TOE_STRAIN]) + TOE_FORCE
    if strain > 0.0:
        return TOE_FORCE / (math.exp(TOE_SHAPE) - 1.0) * (math.exp(TOE_SHAPE * strain / p[TOE_STRAIN]) - 1.0)
    return 0.0


@numba.njit(cache=True, error_model="numpy")
def _cos_pennation(lce: float, p: np.ndarray) -> float:
    s = p[WIDTH] / lce
    return math.sqrt(1.0 - s * s)


@numba.njit(cache=True, error_model="numpy")
def tendon_force(lce: float, length: float, p: np.ndarray) -> float:
    """Tendon force (N) of a fibre of length `lce` in a muscle-tendon unit of length `length`."""
    lce = max(lce, p[MIN_FIBER_LENGTH])
    tendon = length - lce * _cos_pennation(lce, p)
    return p[MAX_FORCE] * _tendon_force(tendon / p[SLACK_LENGTH] - 1.0, p)


@numba.njit(cache=True, error_model="numpy")
def _active_length(ln: float) -> float:
    return math.exp(-(ln - 1.0) ** 2 / KSHAPE_ACTIVE)


@numba.njit(cache=True, error_model="numpy")
def _passive_length(ln: float, p: np.ndarray) -> float:
    if ln <= 1.0:
        return 0.0
    return (math.exp(p[PASSIVE_SHAPE] * (ln - 1.0) / p[MUSCLE_STRAIN]) - 1.0) / p[PASSIVE_SCALE]


@numba.njit(cache=True, error_model="numpy")
def _normalised_speed(a: float, fal: float, force: float) -> float:
    """Fibre speed in units of max speed for a normalised force a·fal·fv (Thelen 2003 eqs. 6-7,
    linear beyond the concentric asymptote and near the eccentric one, as OpenSim extends it)."""
    afl = a * fal
    asymptote = afl * FLEN
    scale = 0.25 + 0.75 * a
    if 0.0 < force < FV_EXTRAPOLATION * asymptote:
        if force <= afl:
            b = afl + force / AF
        else:
            b = (2.0 + 2.0 / AF) * (asymptote - force) / (FLEN - 1.0)
        return scale * (force - afl) / b
    if force <= 0.0:
        f0, b, db = 0.0, afl, 1.0 / AF
    else:
        f0 = FV_EXTRAPOLATION * asymptote
        b = (2.0 + 2.0 / AF) * (asymptote - f0) / (FLEN - 1.0)
        db = -(2.0 + 2.0 / AF) / (FLEN - 1.0)
    slope = scale / b - scale * (f0 - afl) / (b * b) * db
    return scale * (f0 - afl) / b + slope * (force - f0)


@numba.njit(cache=True, error_model="numpy")
def fiber_velocity(a: float, lce: float, length: float, p: np.ndarray) -> float:
    """d lce / dt (m/s): the speed at which the fibre's force balances the tendon's."""
    a = min(max(a, MIN_ACTIVATION), 1.0)
    clamped = lce <= p[MIN_FIBER_LENGTH]
    lce = max(lce, p[MIN_FIBER_LENGTH])
    cos = _cos_pennation(lce, p)
    fse = _tendon_force((length - lce * cos) / p[SLACK_LENGTH] - 1.0, p)
    ln = lce / p[OPTIMAL_LENGTH]
    speed = _normalised_speed(a, _active_length(ln), fse / cos - _passive_length(ln, p))
    if clamped and speed <= 0.0:
        return 0.0  # a fibre at its shortest length stays there
    return speed * p[MAX_SPEED]


@numba.njit(cache=True, error_model="numpy")
def activation_step(a: float, excitation: float, h: float, p: np.ndarray) -> float:
    """Activation after `h` seconds of a constant excitation u, exactly.

    OpenSim 4.6 (measured against it; a is held at a_min or more): da/dt = (u - a) / tau with
    tau = tau_act (0.5 + 1.5 a) while rising and tau_deact / (0.5 + 1.5 a) while falling; a
    approaches u without crossing it, so one branch holds for the whole step. With w = u - a
    and c = 0.5 + 1.5 u both branches separate:
    - rising: c ln(w0 / w1) - 1.5 (w0 - w1) = h / tau_act, solved by Newton in s = ln(w0 / w1),
      on which the left side is monotone;
    - falling: (c - 1.5 w) / w grows by exp(c h / tau_deact), in closed form.
    """
    u = min(max(excitation, 0.0), 1.0)
    x0 = min(max(a, MIN_ACTIVATION), 1.0)
    w0 = u - x0
    if w0 == 0.0:
        return x0
    c = 0.5 + 1.5 * u
    if w0 < 0.0:
        grown = (c / w0 - 1.5) * math.exp(c * h / (p[TAU_DEACTIVATION]))
        return u - c / (grown + 1.5)
    target = h / p[TAU_ACTIVATION]
    s = 0.0
    for _ in range(50):
        e = math.exp(-s)
        ds = (c * s - 1.5 * w0 * (1.0 - e) - target) / (c - 1.5 * w0 * e)
        s -= ds
        if abs(ds) < 1e-14 * (1.0 + s):
            break
    return u - w0 * math.exp(-s)


@numba.njit(cache=True, error_model="numpy")
def _fiber_step(lce0: float, a: float, length: float, h: float, p: np.ndarray) -> tuple[float, float]:
    """Backward Euler: lce1 = lce0 + h v(a, lce1, L), by Newton with a difference quotient;
    returns (lce1, dv/dlce at lce1)."""
    eps = 1e-8 * p[OPTIMAL_LENGTH]
    lmin = p[MIN_FIBER_LENGTH]
    lce, dv = lce0, 0.0
    for _ in range(40):
        v = fiber_velocity(a, lce, length, p)
        dv = (fiber_velocity(a, lce + eps, length, p) - v) / eps
        jac = 1.0 - h * dv
        if jac < 1e-3:  # a locally rising speed curve: keep the step bounded
            jac = 1e-3
        new = max(lce - (lce - lce0 - h * v) / jac, lmin)
        if abs(new - lce) < 1e-12 * p[OPTIMAL_LENGTH]:
            return new, dv
        lce = new
    return lce, dv


@numba.njit(cache=True, error_model="numpy")
def advance(params: np.ndarray, activation: np.ndarray, fiber: np.ndarray, excitation: np.ndarray,
            length: np.ndarray, speed: np.ndarray, dt: float, substeps: int,
            force: np.ndarray, stiffness: np.ndarray) -> None:
    """Advance every muscle `dt` seconds with L moving from `length` at `speed`; write the end
    tendon forces (N) and their derivatives with respect to the end length (N/m)."""
    h = dt / substeps
    for i in range(params.shape[0]):
        p = params[i]
        a, lce, dv = activation[i], fiber[i], 0.0
        end = length[i]
        for k in range(1, substeps + 1):
            a = activation_step(a, excitation[i], h, p)
            end = length[i] + speed[i] * h * k
            lce, dv = _fiber_step(lce, a, end, h, p)
        activation[i], fiber[i] = a, lce
        f = tendon_force(lce, end, p)
        force[i] = f
        # how the last sub-step's fibre, and so the force, answers a change of the end length
        eps = 1e-7
        dv_dl = (fiber_velocity(a, lce, end + eps, p) - fiber_velocity(a, lce, end, p)) / eps
        dlce = h * dv_dl / max(1.0 - h * dv, 1e-3) * eps
        stiffness[i] = (tendon_force(lce + dlce, end + eps, p) - f) / eps


@numba.njit(cache=True, error_model="numpy")
def equilibrium_fiber_length(a: float, length: float, p: np.ndarray) -> float:
    """The fibre length at which a still muscle's fibre and tendon forces balance (what
    OpenSim's `equilibrateMuscles` finds at zero speed), by bisection on the force error."""
    a = min(max(a, MIN_ACTIVATION), 1.0)
    lo, hi = p[MIN_FIBER_LENGTH], max(length, p[MIN_FIBER_LENGTH]) + p[WIDTH]
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        cos = _cos_pennation(mid, p)
        ln = mid / p[OPTIMAL_LENGTH]
        fibre = (a * _active_length(ln) + _passive_length(ln, p)) * cos
        tendon = _tendon_force((length - mid * cos) / p[SLACK_LENGTH] - 1.0, p)
        if fibre < tendon:
            lo = mid
        else:
            hi = mid
        if hi - lo < 1e-14:
            break
    return 0.5 * (lo + hi)


@numba.njit(cache=True, error_model="numpy")
def equilibrate(params: np.ndarray, activation: np.ndarray, length: np.ndarray, fiber: np.ndarray, force: np.ndarray) -> None:
    """Fibre lengths and tendon forces of still muscles in equilibrium at these activations."""
    for i in range(params.shape[0]):
        fiber[i] = equilibrium_fiber_length(activation[i], length[i], params[i])
        force[i] = tendon_force(fiber[i], length[i], params[i])


@numba.njit(cache=True, error_model="numpy")
def tendon_forces(params: np.ndarray, fiber: np.ndarray, length: np.ndarray, force: np.ndarray) -> None:
    """Every muscle's tendon force (N) for its fibre length and muscle-tendon length."""
    for i in range(params.shape[0]):
        force[i] = tendon_force(fiber[i], length[i], params[i])
