"""`l2r.sim.thelen`'s Thelen 2003 muscles as Warp kernels over many worlds, in float32.

The equations, constants and parameter table are the numba module's (`thelen.muscle_parameters`,
one row per muscle, here one row per world and muscle); only the precision differs. The
iterative solves stop at float32's resolution instead of float64's: Newton on the fibre length
at 1e-6 of optimal length, on the activation at 1e-6, the equilibrium bisection after 40 halvings
(the bracket is then below a float32 ulp of the length).
"""

from __future__ import annotations

import warp as wp

# Forward only: no adjoint code to compile (half the cold compile time)
wp.set_module_options({"enable_backward": False})

from l2r.sim import thelen

MuscleRow = wp.types.vector(length=thelen.NUM_PARAMS, dtype=float)

AF = wp.constant(thelen.AF)
FLEN = wp.constant(thelen.FLEN)
KSHAPE_ACTIVE = wp.constant(thelen.KSHAPE_ACTIVE)
FV_EXTRAPOLATION = wp.constant(thelen.FV_EXTRAPOLATION)
MIN_ACTIVATION = wp.constant(thelen.MIN_ACTIVATION)
TOE_FORCE = wp.constant(thelen.TOE_FORCE)
TOE_SHAPE = wp.constant(thelen.TOE_SHAPE)
MAX_FORCE = wp.constant(thelen.MAX_FORCE)
OPTIMAL_LENGTH = wp.constant(thelen.OPTIMAL_LENGTH)
SLACK_LENGTH = wp.constant(thelen.SLACK_LENGTH)
WIDTH = wp.constant(thelen.WIDTH)
MAX_SPEED = wp.constant(thelen.MAX_SPEED)
TAU_ACTIVATION = wp.constant(thelen.TAU_ACTIVATION)
TAU_DEACTIVATION = wp.constant(thelen.TAU_DEACTIVATION)
TOE_STRAIN = wp.constant(thelen.TOE_STRAIN)
TENDON_SLOPE = wp.constant(thelen.TENDON_SLOPE)
MUSCLE_STRAIN = wp.constant(thelen.MUSCLE_STRAIN)
PASSIVE_SHAPE = wp.constant(thelen.PASSIVE_SHAPE)
PASSIVE_SCALE = wp.constant(thelen.PASSIVE_SCALE)
MIN_FIBER_LENGTH = wp.constant(thelen.MIN_FIBER_LENGTH)


@wp.func
def _tendon_curve(strain: float, p: MuscleRow):
    """Normalised tendon force (exponential toe, then linear) and its slope in the strain."""
    if strain > p[TOE_STRAIN]:
        return p[TENDON_SLOPE] * (strain - p[TOE_STRAIN]) + TOE_FORCE, p[TENDON_SLOPE]
    if strain > 0.0:
        scale = TOE_FORCE / (wp.exp(TOE_SHAPE) - 1.0)
        grown = wp.exp(TOE_SHAPE * strain / p[TOE_STRAIN])
        return scale * (grown - 1.0), scale * grown * TOE_SHAPE / p[TOE_STRAIN]
    return 0.0, 0.0


@wp.func
def _cos_pennation(lce: float, p: MuscleRow) -> float:
    s = p[WIDTH] / lce
    return wp.sqrt(1.0 - s * s)


@wp.func
def _tendon(lce_in: float, length: float, p: MuscleRow):
    """Tendon force (N) and its partial derivatives in the muscle-tendon length and in lce."""
    clamped = lce_in <= p[MIN_FIBER_LENGTH]
    lce = wp.max(lce_in, p[MIN_FIBER_LENGTH])
    cos = _cos_pennation(lce, p)
    force, slope = _tendon_curve((length - lce * cos) / p[SLACK_LENGTH] - 1.0, p)
    dforce_dlength = p[MAX_FORCE] * slope / p[SLACK_LENGTH]
    dforce_dlce = -dforce_dlength / cos
    if clamped:
        dforce_dlce = 0.0
    return p[MAX_FORCE] * force, dforce_dlength, dforce_dlce


@wp.func
def tendon_force(lce: float, length: float, p: MuscleRow) -> float:
    force, dforce_dlength, dforce_dlce = _tendon(lce, length, p)
    return force


@wp.func
def _active_length(ln: float) -> float:
    return wp.exp(-(ln - 1.0) * (ln - 1.0) / KSHAPE_ACTIVE)


@wp.func
def _passive_curve(ln: float, p: MuscleRow):
    if ln <= 1.0:
        return 0.0, 0.0
    rate = p[PASSIVE_SHAPE] / p[MUSCLE_STRAIN]
    grown = wp.exp(rate * (ln - 1.0))
    return (grown - 1.0) / p[PASSIVE_SCALE], rate * grown / p[PASSIVE_SCALE]


@wp.func
def _normalised_speed(a: float, fal: float, force: float):
    """`thelen._normalised_speed`: fibre speed in max speeds and its partials in force and fal."""
    afl = a * fal
    asymptote = afl * FLEN
    scale = 0.25 + 0.75 * a
    c = (2.0 + 2.0 / AF) / (FLEN - 1.0)
    if force > 0.0 and force < FV_EXTRAPOLATION * asymptote:
        b = c * (asymptote - force)
        db_df = -c
        db_dafl = c * FLEN
        if force <= afl:
            b = afl + force / AF
            db_df = 1.0 / AF
            db_dafl = 1.0
        v = scale * (force - afl) / b
        return v, (scale - v * db_df) / b, (-scale - v * db_dafl) / b * a
    f0 = 0.0
    b = afl
    db = 1.0 / AF
    if force > 0.0:
        f0 = FV_EXTRAPOLATION * asymptote
        b = c * (asymptote - f0)
        db = -c
    slope = scale / b - scale * (f0 - afl) / (b * b) * db
    return scale * (f0 - afl) / b + slope * (force - f0), slope, -slope * force / afl * a


@wp.func
def fiber_velocity(a_in: float, lce_in: float, length: float, p: MuscleRow):
    """d lce / dt (m/s) and its partial derivatives in lce and in the muscle-tendon length."""
    a = wp.clamp(a_in, MIN_ACTIVATION, 1.0)
    clamped = lce_in <= p[MIN_FIBER_LENGTH]
    lce = wp.max(lce_in, p[MIN_FIBER_LENGTH])
    cos = _cos_pennation(lce, p)
    fse, fse_slope = _tendon_curve((length - lce * cos) / p[SLACK_LENGTH] - 1.0, p)
    ln = lce / p[OPTIMAL_LENGTH]
    fal = _active_length(ln)
    fpe, fpe_slope = _passive_curve(ln, p)
    speed, dv_dforce, dv_dfal = _normalised_speed(a, fal, fse / cos - fpe)
    if clamped and speed <= 0.0:
        return 0.0, 0.0, 0.0
    sin2 = 1.0 - cos * cos
    dforce_dlength = fse_slope / (p[SLACK_LENGTH] * cos)
    dforce_dlce = -(dforce_dlength + fse * sin2 / (lce * cos * cos)) / cos - fpe_slope / p[OPTIMAL_LENGTH]
    dfal_dlce = -2.0 * (ln - 1.0) / KSHAPE_ACTIVE * fal / p[OPTIMAL_LENGTH]
    if clamped:
        dforce_dlce = 0.0
        dfal_dlce = 0.0
    return (speed * p[MAX_SPEED], (dv_dforce * dforce_dlce + dv_dfal * dfal_dlce) * p[MAX_SPEED],
            dv_dforce * dforce_dlength * p[MAX_SPEED])


@wp.func
def activation_step(a: float, excitation: float, h: float, p: MuscleRow) -> float:
    """`thelen.activation_step`: activation after h seconds of a held excitation, exactly."""
    u = wp.clamp(excitation, 0.0, 1.0)
    x0 = wp.clamp(a, MIN_ACTIVATION, 1.0)
    w0 = u - x0
    if w0 == 0.0:
        return x0
    c = 0.5 + 1.5 * u
    if w0 < 0.0:
        grown = (c / w0 - 1.5) * wp.exp(c * h / p[TAU_DEACTIVATION])
        return u - c / (grown + 1.5)
    target = h / p[TAU_ACTIVATION]
    s = float(0.0)
    for _ in range(30):
        e = wp.exp(-s)
        ds = (c * s - 1.5 * w0 * (1.0 - e) - target) / (c - 1.5 * w0 * e)
        s = s - ds
        if wp.abs(ds) < 1.0e-6 * (1.0 + s):
            break
    return u - w0 * wp.exp(-s)


@wp.func
def _fiber_step(lce0: float, a: float, length: float, h: float, p: MuscleRow):
    """`thelen._fiber_step`: backward Euler by bracketed Newton; lce1 and the speed's partials."""
    lmin = p[MIN_FIBER_LENGTH]
    lo = float(-wp.inf)
    hi = float(wp.inf)
    lce = float(lce0)
    dv_dlce = float(0.0)
    dv_dlength = float(0.0)
    for _ in range(40):
        v, dv_dlce, dv_dlength = fiber_velocity(a, lce, length, p)
        g = lce - lce0 - h * v
        if g < 0.0:
            lo = wp.max(lo, lce)
        else:
            hi = wp.min(hi, lce)
        jac = wp.max(1.0 - h * dv_dlce, 1.0e-3)
        new = wp.max(lce - g / jac, lmin)
        if wp.abs(new - lce) < 1.0e-6 * p[OPTIMAL_LENGTH]:
            return new, dv_dlce, dv_dlength
        if not (new > lo and new < hi) and lo > -wp.inf and hi < wp.inf:
            new = 0.5 * (lo + hi)
        lce = new
    return lce, dv_dlce, dv_dlength


@wp.func
def advance_one(a_in: float, lce_in: float, excitation: float, length: float, speed: float, dt: float,
                substeps: int, p: MuscleRow):
    """One muscle over `dt` seconds with L moving from `length` at `speed`: its new activation
    and fibre length, the end tendon force (N) and its derivative in the end length (N/m)."""
    h = dt / float(substeps)
    a = float(a_in)
    lce = float(lce_in)
    dv_dlce = float(0.0)
    dv_dlength = float(0.0)
    end = float(length)
    for k in range(1, substeps + 1):
        a = activation_step(a, excitation, h, p)
        end = length + speed * h * float(k)
        lce, dv_dlce, dv_dlength = _fiber_step(lce, a, end, h, p)
    force, df_dlength, df_dlce = _tendon(lce, end, p)
    # how the last sub-step's fibre, and so the force, answers a change of the end length
    dlce_dlength = h * dv_dlength / wp.max(1.0 - h * dv_dlce, 1.0e-3)
    return a, lce, force, df_dlength + df_dlce * dlce_dlength


@wp.kernel
def advance(params: wp.array2d(dtype=MuscleRow), activation: wp.array2d(dtype=float),
            fiber: wp.array2d(dtype=float), excitation: wp.array2d(dtype=float),
            length: wp.array2d(dtype=float), speed: wp.array2d(dtype=float), dt: float, substeps: int,
            force: wp.array2d(dtype=float), stiffness: wp.array2d(dtype=float)):
    """`thelen.advance`, one thread per world and muscle."""
    w, i = wp.tid()
    a, lce, f, k = advance_one(activation[w, i], fiber[w, i], excitation[w, i], length[w, i], speed[w, i], dt,
                               substeps, params[w, i])
    activation[w, i] = a
    fiber[w, i] = lce
    force[w, i] = f
    stiffness[w, i] = k


@wp.func
def equilibrium_fiber_length(a_in: float, length: float, p: MuscleRow) -> float:
    """`thelen.equilibrium_fiber_length`, by bisection on the force error."""
    a = wp.clamp(a_in, MIN_ACTIVATION, 1.0)
    lo = float(p[MIN_FIBER_LENGTH])
    hi = float(wp.max(length, p[MIN_FIBER_LENGTH]) + p[WIDTH])
    for _ in range(40):
        mid = 0.5 * (lo + hi)
        cos = _cos_pennation(mid, p)
        ln = mid / p[OPTIMAL_LENGTH]
        passive, passive_slope = _passive_curve(ln, p)
        fibre = (a * _active_length(ln) + passive) * cos
        tendon, tendon_slope = _tendon_curve((length - mid * cos) / p[SLACK_LENGTH] - 1.0, p)
        if fibre < tendon:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


@wp.kernel
def equilibrate(params: wp.array2d(dtype=MuscleRow), activation: wp.array2d(dtype=float),
                length: wp.array2d(dtype=float), fiber: wp.array2d(dtype=float), force: wp.array2d(dtype=float)):
    """`thelen.equilibrate`, one thread per world and muscle."""
    w, i = wp.tid()
    fiber[w, i] = equilibrium_fiber_length(activation[w, i], length[w, i], params[w, i])
    force[w, i] = tendon_force(fiber[w, i], length[w, i], params[w, i])


@wp.kernel
def tendon_forces(params: wp.array2d(dtype=MuscleRow), fiber: wp.array2d(dtype=float),
                  length: wp.array2d(dtype=float), force: wp.array2d(dtype=float)):
    """`thelen.tendon_forces`, one thread per world and muscle."""
    w, i = wp.tid()
    force[w, i] = tendon_force(fiber[w, i], length[w, i], params[w, i])
