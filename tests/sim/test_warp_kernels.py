"""The Warp kernels of the runner's force elements (float32, many worlds) against their float64
numba twins at the same states: one world per state of a random-excitation rollout."""

from __future__ import annotations

import copy

import gymnasium
import numpy as np
import pytest
import warp as wp

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim import contact, knee, ligaments, paths, thelen
from l2r.sim import model as body
from l2r.sim.opensim import read_osim
from l2r.sim.warp import contact as warp_contact
from l2r.sim.warp import knee as warp_knee
from l2r.sim.warp import ligaments as warp_ligaments
from l2r.sim.warp import paths as warp_paths
from l2r.sim.warp import thelen as warp_thelen

STATES_AT = (8, 25, 45, 70)  # env steps of the rollout whose states are the worlds


@pytest.fixture(scope="module")
def rollout():
    """(model, states, muscles, osim, muscle list): MjData copies along a seeded random-excitation
    rollout (feet on and off the ground, knees bent and straight), with the muscles' activations
    and fibre lengths at each."""
    env = gymnasium.make("l2r/Run-v0", seed=0).unwrapped
    env.reset()
    actions = np.random.default_rng(0).uniform(0.0, 1.0, (max(STATES_AT), 18))
    states, muscles = [], []
    for step, a in enumerate(actions, start=1):
        info = env.step(a)[-1]
        if step in STATES_AT:
            states.append(copy.copy(env.data))
            muscles.append((info["muscle_activation"], info["fiber_length"]))
    osim = read_osim(body.OSIM_PATH)
    by_name = {m.name: m for m in osim.muscles}
    return env.model, states, muscles, osim, [by_name[n] for n in body.MUSCLES]


def stacked(states, field: str) -> "wp.array":
    """One row per world of an MjData field, as a float32 Warp array (vec3 or spatial-vector
    rows for fields of 3 or 6 columns)."""
    rows = np.stack([getattr(d, field) for d in states]).astype(np.float32)
    kind = {3: wp.vec3, 6: wp.spatial_vector}.get(rows.shape[-1]) if rows.ndim == 3 else None
    return wp.array(rows, dtype=kind or float)


def test_muscle_step_matches_numba(rollout):
    m, states, muscles, osim, muscle_list = rollout
    params = thelen.muscle_parameters(muscle_list)
    worlds, n = len(states), len(params)
    rng = np.random.default_rng(1)
    # the muscles' own lengths through the tendons they pull, and speeds both ways
    switches = paths.PathSwitches(m, muscle_list)
    length = np.stack([d.ten_length[switches.tendons(d.qpos)] for d in states])
    speed = rng.uniform(-0.5, 0.5, (worlds, n))
    excitation = rng.uniform(0.0, 1.0, (worlds, n))
    activation = np.stack([a for a, _ in muscles])
    fiber = np.stack([f for _, f in muscles])
    expected = {k: np.zeros((worlds, n)) for k in ("activation", "fiber", "force", "stiffness")}
    for w in range(worlds):
        expected["activation"][w], expected["fiber"][w] = activation[w], fiber[w]
        thelen.advance(params, expected["activation"][w], expected["fiber"][w], excitation[w], length[w], speed[w],
                       0.0025, 1, expected["force"][w], expected["stiffness"][w])

    f32 = lambda x: wp.array(np.asarray(x, np.float32))  # noqa: E731
    table = wp.array(np.broadcast_to(params, (worlds, n, thelen.NUM_PARAMS)).astype(np.float32), dtype=warp_thelen.MuscleRow)
    got = {"activation": f32(activation), "fiber": f32(fiber), "force": wp.zeros((worlds, n)), "stiffness": wp.zeros((worlds, n))}
    wp.launch(warp_thelen.advance, (worlds, n), [table, got["activation"], got["fiber"], f32(excitation), f32(length),
                                                 f32(speed), 0.0025, 1, got["force"], got["stiffness"]])
    max_force, optimal = params[:, thelen.MAX_FORCE], params[:, thelen.OPTIMAL_LENGTH]
    np.testing.assert_allclose(got["activation"].numpy(), expected["activation"], atol=1e-6)
    assert np.abs(got["fiber"].numpy() - expected["fiber"]).max(axis=0).max() < 1e-5 * optimal.min()
    assert (np.abs(got["force"].numpy() - expected["force"]) / max_force).max() < 1e-4
    assert (np.abs(got["stiffness"].numpy() - expected["stiffness"]) / np.abs(expected["stiffness"]).max()).max() < 1e-3

    # equilibrium at reset, and the tendon force of a given fibre
    want_fiber, want_force = np.zeros((worlds, n)), np.zeros((worlds, n))
    for w in range(worlds):
        thelen.equilibrate(params, activation[w], length[w], want_fiber[w], want_force[w])
    fib, force = wp.zeros((worlds, n)), wp.zeros((worlds, n))
    wp.launch(warp_thelen.equilibrate, (worlds, n), [table, f32(activation), f32(length), fib, force])
    assert np.abs(fib.numpy() - want_fiber).max() < 1e-5 * optimal.min()
    assert (np.abs(force.numpy() - want_force) / max_force).max() < 1e-4
    wp.launch(warp_thelen.tendon_forces, (worlds, n), [table, f32(fiber), f32(length), force])
    want = np.stack([[thelen.tendon_force(fiber[w, i], length[w, i], params[i]) for i in range(n)] for w in range(worlds)])
    assert (np.abs(force.numpy() - want) / max_force).max() < 1e-4


def test_ground_forces_match_numba(rollout):
    m, states, _, osim, _ = rollout
    feet = body.CONTACT_SPHERES
    spheres = np.array([m.geom(g).id for g in feet])
    sphere_body = m.geom_bodyid[spheres]
    root = m.body_rootid[sphere_body]
    radius = m.geom_size[spheres, 0]
    law = contact.contact_law(osim).table()
    element = contact.contact_elements(osim, feet)
    # and the reset state (both feet flat) with its right heel, then its left toe, leaving the
    # ground fast: a cut contact with and without one listed after it in its foot's element
    env = gymnasium.make("l2r/Run-v0").unwrapped
    env.reset(seed=0)
    for lifted in ("r_heel", "l_toe"):
        d = copy.copy(env.data)
        d.cvel[sphere_body[feet.index(lifted)]] = (0.0, 0.0, 0.0, 0.0, 1.0, 0.0)
        states = [*states, d]
    worlds = len(states)
    want = {k: np.zeros((worlds, len(feet), s)) for k, s in (("point", 3), ("local", 3), ("force", 2), ("damping", 2))}
    for w, d in enumerate(states):
        contact.ground_forces(law, radius, spheres, sphere_body, root, element, d.geom_xpos, d.xpos, d.xmat, d.cvel,
                              d.subtree_com, want["point"][w], want["local"][w], want["force"][w], want["damping"][w])
    assert (want["force"][..., 1] > 0).any() and (want["force"][..., 1] == 0).any(), "feet both on and off the ground"
    heel_cut = want["force"][-2, :, 1]
    assert (heel_cut[:2] == 0).all() and (heel_cut[2:] > 0).all(), "the right heel's cut takes its toe"

    got = {k: wp.zeros((worlds, len(feet)), dtype=t) for k, t in
           (("point", wp.vec3), ("local", wp.vec3), ("force", wp.vec2), ("damping", wp.vec2))}
    i32 = lambda x: wp.array(np.asarray(x, np.int32), dtype=int)  # noqa: E731
    wp.launch(warp_contact.ground_forces, (worlds, len(feet)),
              [wp.array(law.astype(np.float32)), wp.array(radius.astype(np.float32)), i32(spheres), i32(sphere_body),
               i32(root), i32(element), stacked(states, "geom_xpos"), stacked(states, "xpos"),
               wp.array(np.stack([d.xmat for d in states]).astype(np.float32).reshape(worlds, -1, 3, 3), dtype=wp.mat33),
               stacked(states, "cvel"), stacked(states, "subtree_com"), got["point"], got["local"], got["force"], got["damping"]])
    weight = 79.66 * 9.80665
    np.testing.assert_allclose(got["point"].numpy(), want["point"], atol=1e-6)
    np.testing.assert_allclose(got["local"].numpy(), want["local"], atol=1e-6)
    np.testing.assert_allclose(got["force"].numpy(), want["force"], atol=1e-4 * weight)
    np.testing.assert_allclose(got["damping"].numpy(), want["damping"], rtol=1e-3, atol=1e-3 * weight)


def test_ligaments_match_numba():
    table = ligaments.ligament_table()
    rng = np.random.default_rng(2)
    q = rng.uniform(-2.5, 2.5, (64, len(table)))  # inside, in the transition and past it, both sides
    spring, damping = np.zeros_like(q), np.zeros_like(q)
    adr = np.arange(len(table))
    for w in range(len(q)):
        ligaments.engage(table, q[w], adr, spring[w], damping[w])
    assert (spring > 0).any() and (spring < 0).any() and (spring == 0).any()
    got_spring, got_damping = wp.zeros(q.shape), wp.zeros(q.shape)
    wp.launch(warp_ligaments.engage, q.shape, [wp.array(table.astype(np.float32)), wp.array(q.astype(np.float32)),
                                               wp.array(adr.astype(np.int32), dtype=int), got_spring, got_damping])
    np.testing.assert_allclose(got_spring.numpy(), spring, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(got_damping.numpy(), damping, rtol=1e-4, atol=1e-6)


def test_path_points_match_numba(rollout):
    m, states, _, osim, muscle_list = rollout
    worlds = len(states)
    i32 = lambda x: wp.array(np.asarray(x, np.int32), dtype=int)  # noqa: E731
    qpos = stacked(states, "qpos")

    # the rollout's poses, and the same with knees and hips swept past their points' ranges
    poses = np.concatenate([np.stack([d.qpos for d in states])] * 3)
    for k, c in enumerate(("knee_angle_r", "knee_angle_l", "hip_flexion_r", "hip_flexion_l")):
        poses[worlds:, m.joint(c).qposadr[0]] = np.linspace(-2.5, 0.6, 2 * worlds)[::(1 if k % 2 else -1)]
    switches = paths.PathSwitches(m, muscle_list)
    tendons = wp.zeros((len(poses), len(muscle_list)), dtype=int)
    wp.launch(warp_paths.select_tendons, tendons.shape,
              [i32(switches.on), i32(warp_paths.switch_of_muscle(switches)), i32(switches.qpos),
               wp.array(switches.low.astype(np.float32)), wp.array(switches.high.astype(np.float32)),
               i32(switches.off_tendon), wp.array(poses.astype(np.float32)), tendons])
    want_tendons = np.stack([switches.tendons(q) for q in poses])
    switched = want_tendons[:, switches.muscle] == switches.off_tendon
    assert switched.any() and not switched.all()
    np.testing.assert_array_equal(tendons.numpy(), want_tendons)

    moving = paths.MovingPoints(m, osim, muscle_list)
    table, slope = warp_paths.moving_tables(moving)
    points = len(moving.site)
    site_pos = wp.zeros((worlds, m.nsite), dtype=wp.vec3)
    wp.launch(warp_paths.place_points, (worlds, points),
              [wp.array(table, dtype=wp.vec3), i32(moving.qpos), i32(moving.site), qpos, site_pos])
    for w, d in enumerate(states):
        want = m.site_pos.copy()
        paths.place_points(moving.table, moving.qpos, moving.site, d.qpos, want)
        np.testing.assert_allclose(site_pos.numpy()[w, moving.site], want[moving.site], atol=1e-6)

    rate = wp.zeros((worlds, points))
    xmat = wp.array(np.stack([d.xmat for d in states]).astype(np.float32).reshape(worlds, -1, 3, 3), dtype=wp.mat33)
    wp.launch(warp_paths.point_rates, (worlds, points),
              [wp.array(slope, dtype=wp.vec3), i32(moving.qpos), i32(moving.site),
               wp.array(moving.neighbours.astype(np.int32), dtype=wp.vec2i), i32(moving.body), qpos,
               stacked(states, "site_xpos"), xmat, rate])
    want_rate = np.zeros((worlds, points))
    for w, d in enumerate(states):
        paths.point_rates(moving.slope, moving.qpos, moving.site, moving.neighbours, moving.body, d.qpos,
                          d.site_xpos, d.xmat, want_rate[w])
    np.testing.assert_allclose(rate.numpy(), want_rate, atol=1e-5)

    speed = stacked(states, "ten_velocity")
    wp.launch(warp_paths.add_point_speeds, (worlds, points), [i32(moving.tendon), i32(moving.dof), rate,
                                                             stacked(states, "qvel"), speed])
    tension = np.random.default_rng(3).uniform(0.0, 3000.0, (worlds, m.ntendon))
    ctrl = wp.zeros((worlds, m.nu))
    wp.launch(warp_paths.point_torques, (worlds, len(moving.torque_actuators)),
              [i32(moving.torque_actuators), i32(moving.actuator), i32(moving.tendon), rate,
               wp.array(tension.astype(np.float32)), ctrl])
    for w, d in enumerate(states):
        want_speed, want_ctrl = d.ten_velocity.copy(), np.zeros(m.nu)
        paths.add_point_speeds(moving.tendon, moving.dof, want_rate[w], d.qvel, want_speed)
        paths.point_torques(moving.torque_actuators, moving.actuator, moving.tendon, want_rate[w], tension[w], want_ctrl)
        np.testing.assert_allclose(speed.numpy()[w], want_speed, atol=1e-5)
        np.testing.assert_allclose(ctrl.numpy()[w], want_ctrl, rtol=1e-5, atol=1e-3)


def test_knee_couplings_follow_the_splines_as_numba(rollout):
    m, states, _, osim, _ = rollout
    coupling = knee.KneeCoupling(m, osim, body.KNEE_SLIDES)
    worlds = len(states)
    eq_data = wp.zeros((worlds, m.neq), dtype=wp.types.vector(length=12, dtype=float))
    wp.launch(warp_knee.follow_splines, (worlds, len(coupling.equality)),
              [wp.array(coupling.equality.astype(np.int32), dtype=int), wp.array(coupling.knee.astype(np.int32), dtype=int),
               wp.array(coupling.breaks.astype(np.float32)), wp.array(coupling.cubics.astype(np.float32)),
               stacked(states, "qpos"), eq_data])
    for w, d in enumerate(states):
        want = np.zeros_like(m.eq_data)
        knee.follow_splines(coupling.equality, coupling.knee, coupling.breaks, coupling.cubics, d.qpos, want)
        np.testing.assert_allclose(eq_data.numpy()[w, coupling.equality], want[coupling.equality], rtol=1e-6, atol=1e-7)
