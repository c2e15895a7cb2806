"""The ligaments against OpenSim's own `calcLimitForce` values."""

import json
from pathlib import Path

import numpy as np
import pytest

from l2r.sim.ligaments import LIGAMENTS, default_limits, ligament_forces

REFERENCE = Path(__file__).parents[2] / "l2r" / "sim" / "assets" / "opensim_reference.json"


@pytest.fixture(scope="module")
def samples():
    p = default_limits()
    ref = json.loads(REFERENCE.read_text())["ligaments"]
    q = np.array([[s["q"][c] for c in p.coordinates] for s in ref])
    qdot = np.array([[s["qdot"][c] for c in p.coordinates] for s in ref])
    forces = np.array([[s["forces"][n] for n in LIGAMENTS] for s in ref])
    return q, qdot, forces


def test_parameters_come_from_the_osim_file():
    p = default_limits()
    assert p.names == LIGAMENTS
    assert p.coordinates == (
        "hip_flexion_r", "knee_angle_r", "ankle_angle_r", "hip_flexion_l", "knee_angle_l", "ankle_angle_l",
    )  # fmt: skip
    np.testing.assert_allclose(np.degrees(p.upper), [120, 10, 20, 120, 10, 20])
    np.testing.assert_allclose(np.degrees(p.lower), [-30, -140, -40, -30, -140, -40])
    np.testing.assert_allclose(p.k_upper, 20 * 180 / np.pi)  # 20 N·m/degree
    np.testing.assert_allclose(p.damping, 0.25 * 180 / np.pi)
    np.testing.assert_allclose(np.degrees(p.transition), 10)


def test_matches_opensim_within_one_percent(samples):
    q, qdot, expected = samples
    got = ligament_forces(q, qdot)
    active = expected != 0.0
    assert active.sum() > 100, "the reference should exercise the limits"
    np.testing.assert_allclose(got[active], expected[active], rtol=0.01)
    np.testing.assert_array_equal(got[~active], 0.0)


def test_transition_is_smooth_and_damping_acts_only_past_the_limit():
    p = default_limits()
    upper = p.upper[0]
    q = np.zeros((5, 6))
    q[:, 0] = upper + np.array([-0.01, 0.0, 0.5, 1.0, 2.0]) * p.transition[0]
    still = ligament_forces(q, np.zeros_like(q))[:, 0]
    moving = ligament_forces(q, np.full_like(q, 3.0))[:, 0]
    assert still[0] == still[1] == 0.0 and moving[0] == moving[1] == 0.0
    np.testing.assert_allclose(still[2], -p.k_upper[0] * 0.5 * 0.5 * p.transition[0])  # step(0.5) = 0.5
    np.testing.assert_allclose(still[4], -p.k_upper[0] * 2 * p.transition[0])  # full stiffness
    np.testing.assert_allclose(moving[4] - still[4], -p.damping[0] * 3.0)
