"""The muscle kernels' analytic derivatives against difference quotients of the same kernels."""

from __future__ import annotations

import numpy as np

from l2r.sim import thelen
from l2r.sim.model import MUSCLES, OSIM_PATH
from l2r.sim.opensim import read_osim

TABLE = thelen.muscle_parameters([{m.name: m for m in read_osim(OSIM_PATH).muscles}[n] for n in MUSCLES])


def random_states(count: int, seed: int = 0):
    """(muscle row, activation, fibre length, muscle-tendon length) spread over slack, taut and
    stretched tendons and short to long fibres, so that every branch of the curves is visited."""
    rng = np.random.default_rng(seed)
    for _ in range(count):
        p = TABLE[rng.integers(len(TABLE))]
        lce = p[thelen.OPTIMAL_LENGTH] * rng.uniform(0.4, 1.8)
        length = p[thelen.SLACK_LENGTH] * rng.uniform(0.98, 1.06) + lce * rng.uniform(0.9, 1.0)
        yield p, rng.uniform(0.0, 1.0), lce, length


def test_fibre_speed_slopes_are_its_derivatives():
    branches = set()
    for p, a, lce, length in random_states(4000):
        v, dv_dlce, dv_dlength = thelen.fiber_velocity(a, lce, length, p)
        eps = 1e-7 * p[thelen.OPTIMAL_LENGTH]
        by_lce = (thelen.fiber_velocity(a, lce + eps, length, p)[0] - thelen.fiber_velocity(a, lce - eps, length, p)[0]) / (2 * eps)
        by_length = (thelen.fiber_velocity(a, lce, length + eps, p)[0] - thelen.fiber_velocity(a, lce, length - eps, p)[0]) / (2 * eps)
        assert abs(dv_dlce - by_lce) < 1e-5 * (1.0 + abs(by_lce)), (p, a, lce, length)
        assert abs(dv_dlength - by_length) < 1e-5 * (1.0 + abs(by_length)), (p, a, lce, length)
        branches.add("slack" if dv_dlength == 0.0 else "shortening" if v < 0.0 else "lengthening")
    assert branches == {"slack", "shortening", "lengthening"}


def test_stiffness_is_the_derivative_of_the_end_force():
    """With one sub-step the stiffness handed to MuJoCo is exactly how the step's end force
    answers a change of the muscle-tendon length, provided the fibre solve found its root (plain
    Newton cycles without one at some tendons near slack)."""
    dt, delta = 0.0025, 1e-7
    checked = 0
    for p, a, lce, length in random_states(500, seed=1):
        params = p[None, :]

        def end_force(at: float) -> tuple[float, float]:
            force, stiffness = np.zeros(1), np.zeros(1)
            thelen.advance(params, np.array([a]), np.array([lce]), np.array([0.7]), np.array([at]), np.zeros(1),
                           dt, 1, force, stiffness)
            return force[0], stiffness[0]

        force, stiffness = end_force(length)
        quotient = (end_force(length + delta)[0] - end_force(length - delta)[0]) / (2 * delta)
        assert abs(stiffness - quotient) < 1e-4 * (1.0 + abs(quotient)), (p, a, lce, length)
        checked += force > 0.0
    assert checked > 100
