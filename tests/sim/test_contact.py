"""The feet's Hunt-Crossley forces (l2r.sim.contact): a contact with no force ends its force
element's list, as Simbody's HuntCrossleyForce does in OpenSim; the obstacles push the feet as
OpenSim's do."""

from __future__ import annotations

import copy

import gymnasium
import numpy as np
import pytest

import l2r.sim  # noqa: F401  (registers the environments)
import l2r.sim.env
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


@pytest.fixture(scope="module")
def both_simulators():
    """The port and OpenSim, each with its forces at the reset pose on flat ground."""
    pytest.importorskip("opensim")
    envs = {name: gymnasium.make(env_id, difficulty=1).unwrapped
            for name, env_id in (("port", "l2r/Run-v0"), ("opensim", "l2r/RunOpenSim-v0"))}
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(l2r.sim.env, "draw_episode", lambda rng, difficulty: ([], (1.0, 1.0)))
        flat = {name: env.reset(seed=0)[1] for name, env in envs.items()}
    yield envs, flat
    for env in envs.values():
        env.close()


def heel_x(info: dict, env) -> float:
    return info["body_pos"][env.body_names.index("calcn_r")][0]


@pytest.mark.parametrize("course", [(0.12, 0.0, 0.1), (0.0, 0.02, 0.08), (0.06, -0.01, 0.15)])
def test_an_obstacle_pushes_the_feet_as_opensims_does(both_simulators, monkeypatch, course):
    """An obstacle (x from the right heel, y, radius) under the feet at the reset pose: each foot
    sphere's push, along the line between the centres and so sideways too (the obstacles lie at
    z = 0, between the feet), frictionless, is OpenSim's within 0.05 N + 0.01 % (up to 17 kN)."""
    envs, flat = both_simulators
    x = heel_x(flat["opensim"], envs["opensim"]) + course[0]
    monkeypatch.setattr(l2r.sim.env, "draw_episode", lambda rng, difficulty: ([(x, *course[1:])], (1.0, 1.0)))
    push = {name: env.reset(seed=0)[1]["contact_force"] - flat[name]["contact_force"] for name, env in envs.items()}
    assert np.abs(push["opensim"]).max() > 1000.0
    np.testing.assert_allclose(push["port"], push["opensim"], rtol=1e-4, atol=0.05)


def test_a_body_thrown_off_an_obstacle_moves_as_in_opensim(both_simulators, monkeypatch):
    """Both heels on an obstacle 12 cm ahead of the right one, muscles idle: over 0.1 s the
    obstacle throws the heels back and up (1.8 kN each at first, gone by the fifth step) and the
    port's pelvis stays within 2 mm of OpenSim's, its heel within 1 cm."""
    envs, flat = both_simulators
    x = heel_x(flat["opensim"], envs["opensim"]) + 0.12
    monkeypatch.setattr(l2r.sim.env, "draw_episode", lambda rng, difficulty: ([(x, 0.0, 0.1)], (1.0, 1.0)))
    paths = {}
    for name, env in envs.items():
        env.reset(seed=0)
        steps = [env.step(np.zeros(18)) for _ in range(10)]
        heel = env.body_names.index("calcn_r")
        paths[name] = (np.array([obs[:3] for obs, *_ in steps]), np.array([info["body_pos"][heel] for *_, info in steps]),
                       np.array([info["contact_force"][0, 2] for *_, info in steps]))
    (pelvis, heel, side), (their_pelvis, their_heel, their_side) = paths["port"], paths["opensim"]
    assert their_side[0] > 1500.0 and their_side[4:].max() == 0.0 and side[4:].max() == 0.0
    assert np.abs(pelvis - their_pelvis).max() < 0.002
    assert np.abs(heel - their_heel).max() < 0.01
