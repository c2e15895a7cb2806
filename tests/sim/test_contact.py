"""The feet's Hunt-Crossley forces: a contact with no force ends its force element's list, as
Simbody's HuntCrossleyForce does in OpenSim (l2r.sim.contact)."""

from __future__ import annotations

import copy

import gymnasium
import numpy as np
import pytest

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim import contact
from l2r.sim import model as body
from l2r.sim.opensim import read_osim

LEAVING = 1.0  # m/s upward: past what the dissipation allows (1 / (1.5 x 1.5 s/m) = 0.44 m/s)


@pytest.fixture(scope="module")
def standing():
    """The model and its reset state, both feet's heels and toes on the ground."""
    env = gymnasium.make("l2r/Run-v0").unwrapped
    env.reset(seed=0)
    return env.model, copy.copy(env.data)


def vertical_forces(m, d, lifted: str | None = None) -> dict[str, float]:
    """Each sphere's vertical force at state d, the body of sphere `lifted` moving up at LEAVING."""
    feet = body.CONTACT_SPHERES
    spheres = np.array([m.geom(g).id for g in feet])
    sphere_body = m.geom_bodyid[spheres]
    cvel = d.cvel.copy()
    if lifted is not None:
        cvel[sphere_body[feet.index(lifted)]] = (0.0, 0.0, 0.0, 0.0, LEAVING, 0.0)
    n = len(feet)
    point, local, force, damping = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 2)), np.zeros((n, 2))
    osim = read_osim(body.OSIM_PATH)
    contact.ground_forces(contact.contact_law(osim).table(), m.geom_size[spheres, 0], spheres, sphere_body,
                          m.body_rootid[sphere_body], contact.contact_elements(osim, feet), d.geom_xpos, d.xpos, d.xmat,
                          cvel, d.subtree_com, point, local, force, damping)
    return dict(zip(feet, force[:, 1]))


def test_each_foot_is_one_force_element():
    elements = contact.contact_elements(read_osim(body.OSIM_PATH), body.CONTACT_SPHERES)
    assert elements[0] == elements[1] != elements[2] == elements[3]


def test_a_heel_leaving_fast_takes_its_toes_force(standing):
    still = vertical_forces(*standing)
    assert all(f > 50.0 for f in still.values()), still
    lifted = vertical_forces(*standing, lifted="r_heel")
    assert lifted["r_heel"] == 0.0 and lifted["r_toe"] == 0.0
    assert lifted["l_heel"] == still["l_heel"] and lifted["l_toe"] == still["l_toe"]


def test_a_toe_leaving_fast_leaves_its_heel_be(standing):
    """The toe is listed after the heel (the sweep along x meets the heel first): its own cut
    ends nothing that comes before it."""
    still = vertical_forces(*standing)
    lifted = vertical_forces(*standing, lifted="l_toe")
    assert lifted["l_toe"] == 0.0 and lifted["l_heel"] == still["l_heel"]
    assert lifted["r_heel"] == still["r_heel"] and lifted["r_toe"] == still["r_toe"]
