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
  millisecond at low activation, where any explicit step of MuJoCo's size diverges. The Newton
  solve takes the speed curve's analytic slope (half the curve evaluations of a difference
  quotient);
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


# The table's lengths proportional to the optimal fibre length (the pennation angle at optimal
# length, the max speed in optimal lengths per second and the 1 % floor are the muscle's own).
OPTIMAL_LENGTH_COLUMNS = [OPTIMAL_LENGTH, WIDTH, MAX_SPEED, MIN_FIBER_LENGTH]


def scale_muscles(table: np.ndarray, strength: np.ndarray | float = 1.0, fiber_length: np.ndarray | float = 1.0,
                  tendon_slack: np.ndarray | float = 1.0) -> None:
    """Scale, in place, each muscle's max isometric force, optimal fibre length and tendon slack
    length by these factors (one per muscle, or one for all): the table `muscle_parameters`
    gives for muscles of those values."""
    table[:, MAX_FORCE] *= strength
    table[:, OPTIMAL_LENGTH_COLUMNS] *= np.reshape(fiber_length, (-1, 1))
    table[:, SLACK_LENGTH] *= tendon_slack


@numba.njit(cache=True, error_model="numpy")
def _tendon_curve(strain: float, p: np.ndarray) -> tuple[float, float]:
    """Normalised tendon force (exponential toe, then linear) and its slope in the strain."""
    if strain > p[TOE_STRAIN]:
        return p[TENDON_SLOPE] * (strain - p[TOE_STRAIN]) + TOE_FORCE, p[TENDON_SLOPE]
    if strain > 0.0:
        scale = TOE_FORCE / (math.exp(TOE_SHAPE) - 1.0)
        grown = math.exp(TOE_SHAPE * strain / p[TOE_STRAIN])
        return scale * (grown - 1.0), scale * grown * TOE_SHAPE / p[TOE_STRAIN]
    return 0.0, 0.0


@numba.njit(cache=True, error_model="numpy")
def _cos_pennation(lce: float, p: np.ndarray) -> float:
    s = p[WIDTH] / lce
    return math.sqrt(1.0 - s * s)


@numba.njit(cache=True, error_model="numpy")
def _tendon(lce: float, length: float, p: np.ndarray) -> tuple[float, float, float]:
    """Tendon force (N) of a fibre of length `lce` in a muscle-tendon unit of length `length`,
    and its partial derivatives in `length` and in `lce` (N/m; d(lce cos)/dlce = 1 / cos)."""
    clamped = lce <= p[MIN_FIBER_LENGTH]
    lce = max(lce, p[MIN_FIBER_LENGTH])
    cos = _cos_pennation(lce, p)
    force, slope = _tendon_curve((length - lce * cos) / p[SLACK_LENGTH] - 1.0, p)
    dforce_dlength = p[MAX_FORCE] * slope / p[SLACK_LENGTH]
    return p[MAX_FORCE] * force, dforce_dlength, 0.0 if clamped else -dforce_dlength / cos


@numba.njit(cache=True, error_model="numpy")
def tendon_force(lce: float, length: float, p: np.ndarray) -> float:
    """Tendon force (N) of a fibre of length `lce` in a muscle-tendon unit of length `length`."""
    return _tendon(lce, length, p)[0]


@numba.njit(cache=True, error_model="numpy")
def _active_length(ln: float) -> float:
    return math.exp(-(ln - 1.0) ** 2 / KSHAPE_ACTIVE)


@numba.njit(cache=True, error_model="numpy")
def _passive_curve(ln: float, p: np.ndarray) -> tuple[float, float]:
    """Normalised passive fibre force and its slope in the normalised length."""
    if ln <= 1.0:
        return 0.0, 0.0
    rate = p[PASSIVE_SHAPE] / p[MUSCLE_STRAIN]
    grown = math.exp(rate * (ln - 1.0))
    return (grown - 1.0) / p[PASSIVE_SCALE], rate * grown / p[PASSIVE_SCALE]


@numba.njit(cache=True, error_model="numpy")
def _normalised_speed(a: float, fal: float, force: float) -> tuple[float, float, float]:
    """Fibre speed in units of max speed for a normalised force a·fal·fv (Thelen 2003 eqs. 6-7,
    linear beyond the concentric asymptote and near the eccentric one, as OpenSim extends it),
    and its partial derivatives in the force and in fal."""
    afl = a * fal
    asymptote = afl * FLEN
    scale = 0.25 + 0.75 * a
    c = (2.0 + 2.0 / AF) / (FLEN - 1.0)
    if 0.0 < force < FV_EXTRAPOLATION * asymptote:
        if force <= afl:
            b, db_df, db_dafl = afl + force / AF, 1.0 / AF, 1.0
        else:
            b, db_df, db_dafl = c * (asymptote - force), -c, c * FLEN
        v = scale * (force - afl) / b
        return v, (scale - v * db_df) / b, (-scale - v * db_dafl) / b * a
    if force <= 0.0:
        f0, b, db = 0.0, afl, 1.0 / AF
    else:
        f0 = FV_EXTRAPOLATION * asymptote
        b = c * (asymptote - f0)
        db = -c
    slope = scale / b - scale * (f0 - afl) / (b * b) * db
    # f0 and b are proportional to afl there, so slope·f0 and the constant part do not move with it
    return scale * (f0 - afl) / b + slope * (force - f0), slope, -slope * force / afl * a


@numba.njit(cache=True, error_model="numpy")
def fiber_velocity(a: float, lce: float, length: float, p: np.ndarray) -> tuple[float, float, float]:
    """d lce / dt (m/s), the speed at which the fibre's force balances the tendon's, and its
    partial derivatives in lce and in the muscle-tendon length (1/s)."""
    a = min(max(a, MIN_ACTIVATION), 1.0)
    clamped = lce <= p[MIN_FIBER_LENGTH]
    lce = max(lce, p[MIN_FIBER_LENGTH])
    cos = _cos_pennation(lce, p)
    fse, fse_slope = _tendon_curve((length - lce * cos) / p[SLACK_LENGTH] - 1.0, p)
    ln = lce / p[OPTIMAL_LENGTH]
    fal = _active_length(ln)
    fpe, fpe_slope = _passive_curve(ln, p)
    speed, dv_dforce, dv_dfal = _normalised_speed(a, fal, fse / cos - fpe)
    if clamped and speed <= 0.0:
        return 0.0, 0.0, 0.0  # a fibre at its shortest length stays there
    # of the force fse / cos - fpe: d(lce cos)/dlce = 1 / cos and dcos/dlce = sin^2 / (lce cos)
    sin2 = 1.0 - cos * cos
    dforce_dlength = fse_slope / (p[SLACK_LENGTH] * cos)
    dforce_dlce = -(dforce_dlength + fse * sin2 / (lce * cos * cos)) / cos - fpe_slope / p[OPTIMAL_LENGTH]
    if clamped:
        dforce_dlce = 0.0
    dfal_dlce = 0.0 if clamped else -2.0 * (ln - 1.0) / KSHAPE_ACTIVE * fal / p[OPTIMAL_LENGTH]
    return (speed * p[MAX_SPEED], (dv_dforce * dforce_dlce + dv_dfal * dfal_dlce) * p[MAX_SPEED],
            dv_dforce * dforce_dlength * p[MAX_SPEED])


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
def _fiber_step(lce0: float, a: float, length: float, h: float, p: np.ndarray) -> tuple[float, float, float]:
    """Backward Euler: lce1 = lce0 + h v(a, lce1, L), the root of g = lce - lce0 - h v, by Newton
    kept inside the bracket its iterates have found. Where the tendon goes slack the speed's
    slope jumps, and plain Newton can cycle there for ever; a step that leaves the bracket
    bisects it instead. Returns lce1 and the speed's partial derivatives at the last iterate."""
    lmin = p[MIN_FIBER_LENGTH]
    lo, hi = -np.inf, np.inf  # g < 0 at lo, g >= 0 at hi
    lce, dv_dlce, dv_dlength = lce0, 0.0, 0.0
    for _ in range(80):
        v, dv_dlce, dv_dlength = fiber_velocity(a, lce, length, p)
        g = lce - lce0 - h * v
        if g < 0.0:
            lo = max(lo, lce)
        else:
            hi = min(hi, lce)
        jac = 1.0 - h * dv_dlce
        if jac < 1e-3:  # a locally rising speed curve: keep the step bounded
            jac = 1e-3
        new = max(lce - g / jac, lmin)
        if abs(new - lce) < 1e-12 * p[OPTIMAL_LENGTH]:
            return new, dv_dlce, dv_dlength
        if not lo < new < hi and lo > -np.inf and hi < np.inf:
            new = 0.5 * (lo + hi)
        lce = new
    return lce, dv_dlce, dv_dlength


@numba.njit(cache=True, error_model="numpy")
def advance(params: np.ndarray, activation: np.ndarray, fiber: np.ndarray, excitation: np.ndarray,
            length: np.ndarray, speed: np.ndarray, dt: float, substeps: int,
            force: np.ndarray, stiffness: np.ndarray) -> None:
    """Advance every muscle `dt` seconds with L moving from `length` at `speed`; write the end
    tendon forces (N) and their derivatives with respect to the end length (N/m)."""
    h = dt / substeps
    for i in range(params.shape[0]):
        p = params[i]
        a, lce, dv_dlce, dv_dlength = activation[i], fiber[i], 0.0, 0.0
        end = length[i]
        for k in range(1, substeps + 1):
            a = activation_step(a, excitation[i], h, p)
            end = length[i] + speed[i] * h * k
            lce, dv_dlce, dv_dlength = _fiber_step(lce, a, end, h, p)
        activation[i], fiber[i] = a, lce
        f, df_dlength, df_dlce = _tendon(lce, end, p)
        force[i] = f
        # how the last sub-step's fibre, and so the force, answers a change of the end length
        dlce_dlength = h * dv_dlength / max(1.0 - h * dv_dlce, 1e-3)
        stiffness[i] = df_dlength + df_dlce * dlce_dlength


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
        fibre = (a * _active_length(ln) + _passive_curve(ln, p)[0]) * cos
        tendon = _tendon_curve((length - mid * cos) / p[SLACK_LENGTH] - 1.0, p)[0]
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
