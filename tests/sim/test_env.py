"""RunEnv: the 2017 observation, reward, done rules, episode generation and determinism."""

import json
import math
import warnings
from pathlib import Path

import gymnasium
from gymnasium.utils.env_checker import check_env
import mujoco
import numpy as np
import pytest

import l2r.sim  # noqa: F401  (registers l2r/Run-v0)
import l2r.sim.env
from l2r.sim.env import FALL_HEIGHT, MAX_STEPS, NO_OBSTACLE, RunEnv, draw_episode, next_obstacle
from l2r.sim.ligaments import LIGAMENTS, default_limits, ligament_forces
from l2r.sim.model import OSIM_PATH
from l2r.sim.opensim import read_osim
from l2r.sim.paths import PathSwitches
from l2r.sim.wrappers import ActionRepeat

REFERENCE = Path(__file__).parents[2] / "l2r" / "sim" / "assets" / "opensim_reference.json"
TRACKED = ("head", "pelvis", "torso", "toes_l", "toes_r", "talus_l", "talus_r")
JOINTS = ("hip_flexion_r", "knee_angle_r", "ankle_angle_r", "hip_flexion_l", "knee_angle_l", "ankle_angle_l")


@pytest.fixture(scope="module")
def reference():
    return json.loads(REFERENCE.read_text())


def random_actions(n, seed=0):
    return np.random.default_rng(seed).uniform(0.0, 1.0, (n, 18))


def rollout(env, actions, seed):
    """Observations, rewards and flags of an episode, stopping at its end."""
    obs, _ = env.reset(seed=seed)
    out = [obs]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        assert "diverged" not in info
        out.append(np.append(obs, [reward, terminated, truncated]))
        if terminated or truncated:
            break
    return out


def expected_observation(env):
    """The 2017 observation rebuilt from MuJoCo by name, independently of the env's gather."""
    m, d = env.model, env.data
    q = {j: d.qpos[m.joint(j).qposadr[0]] for j in ("pelvis_tilt", "pelvis_tx", "pelvis_ty") + JOINTS}
    v = {j: d.qvel[m.joint(j).dofadr[0]] for j in q}
    mass = m.body_mass[1:]
    com = (mass[:, None] * d.xipos[1:]).sum(0) / mass.sum()
    jac = np.zeros((3, m.nv))
    mujoco.mj_jacSubtreeCom(m, d, jac, 0)
    com_vel = jac @ d.qvel
    obs = [q["pelvis_tilt"], q["pelvis_tx"], q["pelvis_ty"], v["pelvis_tilt"], v["pelvis_tx"], v["pelvis_ty"]]
    obs += [q[j] for j in JOINTS] + [v[j] for j in JOINTS]
    obs += [com[0], com[1], com_vel[0], com_vel[1]]
    for b in TRACKED:
        obs += list(d.xpos[m.body(b).id][:2])
    obs += list(env.psoas) + list(next_obstacle(env.obstacles, q["pelvis_tx"]))
    return np.array(obs)


# ------------------------------------------------------------------------------ observation


def test_reset_observation_matches_opensim_within_a_millimetre(reference):
    env = RunEnv()
    obs, _ = env.reset(seed=0)
    assert obs.shape == (41,) and obs.dtype == np.float32
    assert env.observation_space.contains(obs)
    for rollout_ in reference["rollouts"]:
        np.testing.assert_allclose(obs, rollout_["reset_observation"], rtol=0, atol=1e-3)
    assert tuple(obs[38:]) == NO_OBSTACLE and tuple(obs[36:38]) == (1.0, 1.0)


def test_observation_layout_along_a_rollout():
    env = RunEnv(difficulty=2)
    obs, _ = env.reset(seed=3)
    np.testing.assert_allclose(obs, expected_observation(env), rtol=1e-5, atol=1e-6)
    for a in random_actions(40):
        obs, _, terminated, truncated, _ = env.step(a)
        np.testing.assert_allclose(obs, expected_observation(env), rtol=1e-5, atol=1e-5)
        if terminated or truncated:
            break
    assert np.any(obs[3:18] != 0.0), "velocities should be observed"


def test_next_obstacle_is_the_first_not_yet_passed():
    course = [(1.0, 0.01, 0.1), (2.0, -0.02, 0.2)]
    assert next_obstacle(course, 0.5) == pytest.approx((0.5, 0.01, 0.1))
    assert next_obstacle(course, 1.1) == pytest.approx((-0.1, 0.01, 0.1))  # still over it
    assert next_obstacle(course, 1.15) == pytest.approx((0.85, -0.02, 0.2))
    assert next_obstacle(course, 2.3) == NO_OBSTACLE
    assert next_obstacle([], 0.0) == NO_OBSTACLE


# ------------------------------------------------------------------------------ reward, ligaments


def test_reward_is_distance_minus_ligament_penalty():
    env = RunEnv()
    env.reset(seed=1)
    m, d = env.model, env.data
    lig_q = [m.joint(c).qposadr[0] for c in default_limits().coordinates]
    lig_v = [m.joint(c).dofadr[0] for c in default_limits().coordinates]
    x = d.qpos[m.joint("pelvis_tx").qposadr[0]]
    # Hip extensors at full excitation drive the hips past their -30 degree limit.
    extend_hips = np.array([name.startswith(("glut_max", "hamstrings")) for name in env.muscle_names], float)
    strained = 0
    for a in [extend_hips] * 100:
        _, reward, terminated, truncated, info = env.step(a)
        forces = ligament_forces(d.qpos[lig_q], d.qvel[lig_v])
        np.testing.assert_allclose(info["ligament_force"], forces, rtol=1e-12, atol=1e-9)
        new_x = d.qpos[m.joint("pelvis_tx").qposadr[0]]
        assert reward == pytest.approx(new_x - x - math.sqrt(np.sum(forces**2)) * 1e-7, rel=1e-12, abs=1e-15)
        assert info["distance"] == new_x
        strained += np.any(forces != 0)
        x = new_x
        if terminated or truncated:
            break
    assert strained, "full hip extension should push the hips past their ligament limit"


def test_ligaments_act_on_the_joints_every_physics_step():
    """After every physics step the ligaments are set for the joint positions: springs as
    generalised forces, damping as joint damping."""
    env = RunEnv()
    env.reset(seed=0)
    m, d, physics = env.model, env.data, env._physics
    lig_q = [m.joint(c).qposadr[0] for c in default_limits().coordinates]
    lig_v = [m.joint(c).dofadr[0] for c in default_limits().coordinates]
    strained = 0
    for a in np.repeat(random_actions(60, seed=2), env.substeps, axis=0):
        physics.excitation[:] = a
        physics.step(1)
        q = d.qpos[lig_q]
        springs = ligament_forces(q, np.zeros(6))
        np.testing.assert_allclose(d.qfrc_applied[lig_v], springs, rtol=0, atol=1e-9)
        np.testing.assert_allclose(m.dof_damping[lig_v], springs - ligament_forces(q, np.ones(6)), rtol=0, atol=1e-9)
        strained += np.any(springs != 0)
    assert strained, "some physics step should strain a ligament"


# ------------------------------------------------------------------------------ done rules


def test_terminates_when_the_pelvis_drops_below_065():
    env = RunEnv()
    env.reset(seed=0)
    for step in range(1, 400):
        obs, _, terminated, truncated, info = env.step(np.zeros(18))
        assert "diverged" not in info and not truncated
        if terminated:
            break
        assert obs[2] >= FALL_HEIGHT
    assert terminated and obs[2] < FALL_HEIGHT
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(18))


def test_truncates_at_max_steps():
    assert RunEnv().max_steps == MAX_STEPS == 1000
    env = RunEnv(max_steps=3)
    env.reset(seed=0)
    flags = [env.step(np.full(18, 0.05))[3] for _ in range(3)]
    assert flags == [False, False, True]
    with pytest.raises(RuntimeError):
        env.step(np.zeros(18))


@pytest.mark.parametrize("steps_before", [0, 3])
def test_a_diverging_simulation_ends_the_episode(steps_before, tmp_path, monkeypatch, caplog):
    monkeypatch.chdir(tmp_path)  # MuJoCo writes MUJOCO_LOG.TXT into the working directory
    env = RunEnv()
    env.reset(seed=0)
    for _ in range(steps_before):
        env.step(np.full(18, 0.1))
    env.data.qvel[env.model.joint("knee_angle_r").dofadr[0]] = 1e12  # MuJoCo resets its data
    _, reward, terminated, _, info = env.step(np.zeros(18))
    assert terminated and info["diverged"] and reward == 0.0
    assert "diverged" in caplog.text
    env.reset(seed=0)
    assert "diverged" not in env.step(np.zeros(18))[4]


def test_step_before_reset_is_an_error():
    with pytest.raises(RuntimeError, match="reset"):
        RunEnv().step(np.zeros(18))


# ------------------------------------------------------------------------------ difficulty


def test_episode_distributions():
    rng = np.random.default_rng(0)
    assert draw_episode(rng, 0) == ([], (1.0, 1.0))
    courses = [draw_episode(rng, 1) for _ in range(3000)]
    assert all(psoas == (1.0, 1.0) for _, psoas in courses)
    obstacles = np.array([c for c, _ in courses])  # (n, 3, 3)
    x, y, r = obstacles[..., 0], obstacles[..., 1], obstacles[..., 2]
    assert np.all(np.diff(x, axis=1) >= 0), "sorted by x"
    assert x.min() >= 1.0 and x.max() <= 5.0 and abs(x.mean() - 3.0) < 0.05
    assert r.min() >= 0.05 and abs((r - 0.05).mean() - 0.05) < 0.003
    ratio = y / r
    assert ratio.min() >= -0.25 and ratio.max() <= 0.25 and abs(ratio.std() - 0.5 / math.sqrt(12)) < 0.005
    strengths = np.array([draw_episode(rng, 2)[1] for _ in range(3000)])
    assert strengths.min() >= 0.5 and strengths.max() < 1.6
    assert abs(strengths.mean() - 1.0) < 0.01 and abs(strengths.std() - 0.1) < 0.01


def test_difficulty_places_obstacles_and_scales_the_psoas():
    env = RunEnv(difficulty=2)
    m = env.model
    base = env.max_isometric_force
    obs, _ = env.reset(seed=7)
    assert len(env.obstacles) == 3 and env.psoas != (1.0, 1.0)
    for i, (x, y, r) in enumerate(env.obstacles):
        g = m.geom(f"obstacle_{i}")
        np.testing.assert_allclose(g.pos, [x, y, 0.0])
        assert g.size[0] == r and m.geom_rbound[g.id] == r
    np.testing.assert_allclose(obs[38:], env.obstacles[0], rtol=1e-6)  # pelvis x is 0 at reset
    np.testing.assert_allclose(obs[36:38], env.psoas, rtol=1e-6)
    left, right = env.psoas
    scale = np.ones(18)
    scale[env.muscle_names.index("iliopsoas_r")] = right
    scale[env.muscle_names.index("glut_max_l")] = left  # the 2017 code's index 11
    np.testing.assert_allclose(env.max_isometric_force, base * scale)

    fixed = RunEnv(difficulty=2, left_psoas="iliopsoas_l")
    fixed.reset(seed=7)
    assert fixed.psoas == env.psoas
    scale = np.ones(18)
    scale[3], scale[12] = right, left
    np.testing.assert_allclose(fixed.max_isometric_force, base * scale)

    # Back to flat ground: obstacles parked, strengths restored.
    obs, _ = env.reset(seed=7, options={"difficulty": 0})
    assert env.obstacles == [] and tuple(obs[38:]) == NO_OBSTACLE
    np.testing.assert_allclose(env.max_isometric_force, base)
    assert all(m.geom(f"obstacle_{i}").pos[0] < -10 for i in range(3))


def test_the_course_pushes_the_feet_and_leaves_with_the_episode(monkeypatch):
    """An obstacle drawn under the right heel pushes it at reset, sideways too (the ground's
    forces have no z); the next episode's flat ground, and then an obstacle far ahead, push
    nothing."""
    env = RunEnv(difficulty=1)
    heel = env.reset(seed=0)[1]["body_pos"][env.body_names.index("calcn_r")]
    courses = iter([[(heel[0], 0.0, 0.1)], [], [(3.0, 0.0, 0.1)]])
    monkeypatch.setattr(l2r.sim.env, "draw_episode", lambda rng, difficulty: (next(courses), (1.0, 1.0)))
    pushed = env.reset(seed=0)[1]["contact_force"]
    assert abs(pushed[0, 2]) > 100.0 and not pushed[[1, 3], 2].any()
    for _ in range(2):
        assert not env.reset(seed=0)[1]["contact_force"][:, 2].any()


def test_bad_difficulty_and_options():
    with pytest.raises(ValueError, match="difficulty"):
        RunEnv(difficulty=3)
    with pytest.raises(ValueError, match="left_psoas"):
        RunEnv(left_psoas="psoas")
    with pytest.raises(ValueError, match="difficulty"):
        RunEnv().reset(options={"difficulty": -1})


# ------------------------------------------------------------------------------ determinism, actions


def test_same_seed_and_actions_give_the_same_trajectory_bit_for_bit():
    actions = random_actions(80, seed=5)
    first = rollout(RunEnv(difficulty=2), actions, seed=11)
    second = rollout(RunEnv(difficulty=2, seed=11), actions, seed=None)  # constructor seed
    used = RunEnv(difficulty=2)
    for seed in (3, 4):  # nothing of earlier episodes may leak into the next one
        rollout(used, actions[:30], seed=seed)
    third = rollout(used, actions, seed=11)
    assert len(first) == len(second) == len(third) > 1
    for a, b, c in zip(first, second, third):
        assert np.array_equal(a, b) and np.array_equal(a, c)
    other = rollout(RunEnv(difficulty=2), actions, seed=12)
    assert not np.array_equal(first[0], other[0])  # another course, other psoas


def test_bad_actions_raise_clear_errors():
    env = RunEnv()
    env.reset(seed=0)
    for bad in (np.full(18, np.nan), np.r_[np.zeros(17), np.inf], np.r_[-np.inf, np.zeros(17)]):
        with pytest.raises(ValueError, match="NaN or inf"):
            env.step(bad)
    for shape in ((17,), (19,), (1, 18), ()):
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros(shape))
    with pytest.raises(ValueError):
        env.step(["a"] * 18)
    env.step([0.1] * 18)  # a list is fine
    env.step(np.full(18, 1e200))  # huge but finite: clipped, not rejected


def test_out_of_range_excitations_are_clipped():
    raw = np.linspace(-2.0, 3.0, 18)
    clipped_env, raw_env = RunEnv(), RunEnv()
    clipped_env.reset(seed=0)
    raw_env.reset(seed=0)
    for _ in range(3):
        a = clipped_env.step(np.clip(raw, 0, 1))[0]
        b = raw_env.step(raw)[0]
        assert np.array_equal(a, b)
    assert raw_env.excitation.min() == 0.0 and raw_env.excitation.max() == 1.0


# ------------------------------------------------------------------------------ info, wrappers


def test_info_carries_what_a_logger_needs():
    env = RunEnv()
    _, info = env.reset(seed=0)
    m, d = env.model, env.data
    shapes = {
        "body_pos": (m.nbody, 3), "body_quat": (m.nbody, 4), "muscle_activation": (18,),
        "muscle_length": (18,), "muscle_force": (18,), "fiber_length": (18,),
        "ligament_force": (len(LIGAMENTS),), "contact_force": (4, 3),
    }  # fmt: skip
    for _ in range(5):
        _, _, _, _, info = env.step(np.full(18, 0.3))
    assert set(info) == set(shapes) | {"distance"}
    for key, shape in shapes.items():
        assert info[key].shape == shape, key
    assert len(env.body_names) == m.nbody and env.body_names[m.body("pelvis").id] == "pelvis"
    np.testing.assert_array_equal(info["body_pos"], d.xpos)
    np.testing.assert_allclose(np.linalg.norm(info["body_quat"], axis=1), 1.0)
    # each muscle's length is that of the tendon its conditional point selects
    muscles = {mu.name: mu for mu in read_osim(OSIM_PATH).muscles}
    switches = PathSwitches(m, [muscles[n] for n in env.muscle_names])
    np.testing.assert_array_equal(info["muscle_length"], d.ten_length[switches.tendons(d.qpos)])
    assert np.all(info["muscle_activation"] >= 0.01) and np.all(info["muscle_force"] >= 0)
    # Copies, not views of the live simulation: a logger may keep them.
    live = (d.xpos, d.xquat, d.ten_length, d.actuator_force, d.qpos, d.efc_force)
    for key, value in info.items():
        assert not any(np.shares_memory(value, array) for array in live), key


def test_ground_pushes_each_foot_sphere_by_hunt_crossley():
    """At reset, at rest, each sphere's ground force is 4/3 k^1.5 sqrt(R) d^1.5 with
    k = 600000^(2/3) / 2, straight up; together about twice the body's weight, as in OpenSim
    (the feet start 2.8 to 3.9 cm deep)."""
    env = RunEnv()
    _, info = env.reset(seed=0)
    d = env.data
    k = 600000 ** (2 / 3) / 2
    for i, sphere in enumerate(("r_heel", "r_toe", "l_heel", "l_toe")):
        depth = 0.05 - d.geom_xpos[env.model.geom(sphere).id][1]
        assert 0.027 < depth < 0.04
        np.testing.assert_allclose(info["contact_force"][i], [0.0, 4 / 3 * k**1.5 * np.sqrt(0.05) * depth**1.5, 0.0], atol=1e-9)
    weight = 79.66 * 9.80665
    assert 1.9 * weight < info["contact_force"][:, 1].sum() < 2.1 * weight


def test_ground_forces_reach_the_body_through_the_contact_actuators():
    """What MuJoCo applies along each contact actuator is the ground force the env computed
    (the explicit part; only the speed change over the step goes through the damping)."""
    env = RunEnv()
    env.reset(seed=0)
    m, d = env.model, env.data
    env._physics.drive()
    mujoco.mj_fwdActuation(m, d)
    for i, sphere in enumerate(("r_heel", "r_toe", "l_heel", "l_toe")):
        for axis, name in enumerate(("x", "y")):
            assert d.actuator_force[m.actuator(f"{sphere}_{name}").id] == pytest.approx(env._physics.ground_force[i, axis], abs=1e-9)
        site = m.site(f"{sphere}_contact").id
        assert d.site_xpos[site][1] == pytest.approx(-0.5 * (0.05 - d.geom_xpos[m.geom(sphere).id][1]))


def test_action_repeat_sums_rewards_and_stops_at_the_end():
    actions = random_actions(6, seed=3)
    env = RunEnv(max_steps=4)
    env.reset(seed=0)
    single = [env.step(a)[1] for a in np.repeat(actions[:1], 4, axis=0)]
    wrapped = ActionRepeat(RunEnv(max_steps=4), repeat=3)
    wrapped.reset(seed=0)
    _, reward, _, truncated, info = wrapped.step(actions[0])
    assert reward == pytest.approx(sum(single[:3]), rel=1e-12, abs=1e-15) and not truncated
    assert info["inner_steps"] == 3
    _, reward, _, truncated, info = wrapped.step(actions[0])
    assert truncated and info["inner_steps"] == 1 and reward == pytest.approx(single[3], rel=1e-12, abs=1e-15)
    with pytest.raises(ValueError):
        ActionRepeat(RunEnv(), repeat=0)


def test_gymnasium_make():
    # gymnasium.make wraps the env in its passive checker; any complaint fails the test.
    warnings.simplefilter("error")
    env = gymnasium.make("l2r/Run-v0", difficulty=1)
    assert isinstance(env.unwrapped, RunEnv) and env.unwrapped.difficulty == 1
    assert env.spec.max_episode_steps is None  # RunEnv truncates itself; no TimeLimit on top
    wrapper = env
    while wrapper is not env.unwrapped:
        assert not isinstance(wrapper, gymnasium.wrappers.TimeLimit)
        wrapper = wrapper.env
    obs, _ = env.reset(seed=0)
    assert obs.shape == (41,)
    obs, reward, terminated, truncated, info = env.step(env.action_space.sample())
    assert np.isfinite(reward) and "contact_force" in info


def test_passes_gymnasiums_env_checker():
    warnings.simplefilter("error")
    warnings.filterwarnings("ignore", message=".*infinity")  # unbounded observations are intended
    check_env(RunEnv(difficulty=2), skip_render_check=True)
