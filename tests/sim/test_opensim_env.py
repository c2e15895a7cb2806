"""RunOpenSimEnv: the 2017 environment on real OpenSim 4.6, against the reference rollouts, the
MuJoCo env's layout, and the commands that take an env id: `l2r eval` and `l2r-actor`."""

import json
import math
import os
import subprocess
import sys
import uuid

import gymnasium
import numpy as np
import pytest
import zenoh

import l2r.sim  # noqa: F401  (registers the envs)
import l2r.sim.env
import l2r.sim.opensim_env as opensim_env
from l2r.actors.__main__ import build_parser as actor_parser
from l2r.episodes.read import read_episode
from l2r.evaluate import build_parser as eval_parser
from l2r.learner.checkpoint import save_checkpoint
from l2r.learner.sac import SACConfig, init_state
from l2r.protocol.keys import Keys
from l2r.protocol.session import session_config
from l2r.sim.env import FALL_HEIGHT, MAX_STEPS, NO_OBSTACLE
from l2r.sim.ligaments import LIGAMENTS, default_limits, ligament_forces
from l2r.sim.opensim_env import RunOpenSimEnv
from l2r.sim.wrappers import ActionRepeat
from tests.conftest import ROOT, free_port

opensim = pytest.importorskip("opensim")

REFERENCE = ROOT / "l2r" / "sim" / "assets" / "opensim_reference.json"
SUBPROCESS_ENV = {**os.environ, "PYTHONPATH": str(ROOT)}


@pytest.fixture(scope="module")
def reference():
    return json.loads(REFERENCE.read_text())


@pytest.fixture(scope="module")
def env():
    """One env for the tests that reset it before use (building one costs about 0.2 s)."""
    return RunOpenSimEnv()


def newton(env):
    """The world force on the body from the contacts, and the mass times the centre of mass
    acceleration less gravity: equal when the contact forces are complete and signed right."""
    m, s = env.osim_model, env.state
    m.realizeAcceleration(s)
    return m.getTotalMass(s) * (m.calcMassCenterAcceleration(s).to_numpy() - m.getGravity().to_numpy())


# ------------------------------------------------------------------------------ the 2017 backend


def test_reset_observation_is_opensims_and_matches_run_v0(env, reference):
    obs, _ = env.reset(seed=0)
    assert obs.shape == (41,) and obs.dtype == np.float32 and env.observation_space.contains(obs)
    for rollout in reference["rollouts"]:
        np.testing.assert_array_equal(obs, np.float32(rollout["reset_observation"]))
    mujoco_obs, _ = gymnasium.make("l2r/Run-v0").reset(seed=0)
    np.testing.assert_allclose(obs, mujoco_obs, rtol=0, atol=1e-6)  # the port agrees to 3e-7


def test_zero_excitation_reproduces_the_reference_rollout(env, reference):
    """Zero excitation until the fall, as OpenSim computed it for the reference file: the same
    numbers to the float32 rounding of the observation, and the fall at the same step."""
    expected = reference["rollouts"][0]
    assert expected["label"] == "zero excitation from the default pose"
    env.reset(seed=0)
    observed = []
    for step in range(1, expected["steps"] + 1):
        obs, _, terminated, truncated, info = env.step(np.zeros(18))
        assert "diverged" not in info and not truncated
        observed.append(obs[:18])
        if terminated:
            break
    np.testing.assert_allclose(observed, np.float32(expected["trajectory_first18"][:step]), rtol=1e-6, atol=1e-6)
    assert step == expected["first_step_pelvis_y_below_0_65"] == 142
    assert observed[-1][2] < FALL_HEIGHT <= observed[-2][2]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(18))


def test_new_excitations_act_from_the_start_of_the_step(env, reference):
    """The reference's second rollout (0.5 from the first step) set its excitations after its
    integrator had started, so its first step began from zero-excitation derivatives. The env
    restarts the integrator when the excitations change: against an integration at accuracy
    1e-10, its first step is many times closer than the reference's, and the two agree later."""
    expected = np.array(reference["rollouts"][1]["trajectory_first18"][:10])

    def rollout(env):
        env.reset(seed=0)
        return np.array([env.step(np.full(18, 0.5))[0][:18] for _ in range(10)], dtype=np.float64)

    observed, exact = rollout(env), rollout(RunOpenSimEnv(accuracy=1e-10))
    assert np.abs(observed[0] - exact[0]).max() < np.abs(expected[0] - exact[0]).max() / 20
    np.testing.assert_allclose(observed, expected, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(observed[-1], expected[-1], rtol=0, atol=1e-4)


def test_same_seed_and_actions_give_the_same_trajectory_bit_for_bit():
    actions = np.random.default_rng(5).uniform(0.0, 1.0, (40, 18))

    def rollout(env, seed):
        out = [env.reset(seed=seed)[0]]
        for a in actions:
            obs, reward, terminated, truncated, _ = env.step(a)
            out.append(np.append(obs, [reward, terminated, truncated]))
            if terminated or truncated:
                break
        return out

    used = RunOpenSimEnv(difficulty=2)
    rollout(used, seed=3)  # nothing of an earlier episode may leak into the next one
    first, second = rollout(used, seed=11), rollout(RunOpenSimEnv(difficulty=2, seed=11), seed=None)
    assert len(first) == len(second) > 1
    for a, b in zip(first, second):
        assert np.array_equal(a, b)


# ------------------------------------------------------------------------------ reward, done rules


def test_reward_is_distance_minus_ligament_penalty(env):
    env.reset(seed=1)
    lig = default_limits()
    x = 0.0
    # Hip extensors at full excitation drive the hips past their -30 degree limit.
    extend_hips = np.array([name.startswith(("glut_max", "hamstrings")) for name in env.muscle_names], float)
    strained = 0
    for _ in range(60):
        obs, reward, terminated, truncated, info = env.step(extend_hips)
        coordinates = env.osim_model.getCoordinateSet()
        q = [coordinates.get(c).getValue(env.state) for c in lig.coordinates]
        qdot = [coordinates.get(c).getSpeedValue(env.state) for c in lig.coordinates]
        # OpenSim's calcLimitForce against l2r's own formula of the same ligaments.
        np.testing.assert_allclose(info["ligament_force"], ligament_forces(q, qdot), rtol=1e-9, atol=1e-9)
        forces = info["ligament_force"]
        assert info["distance"] == pytest.approx(float(obs[1]), abs=1e-6)
        assert reward == pytest.approx(info["distance"] - x - math.sqrt(np.sum(forces**2)) * 1e-7, rel=1e-12, abs=1e-15)
        x = info["distance"]
        strained += np.any(forces != 0)
        if terminated or truncated:
            break
    assert strained, "full hip extension should push the hips past their ligament limit"


def test_truncates_at_max_steps():
    assert RunOpenSimEnv().max_steps == MAX_STEPS == 1000
    env = RunOpenSimEnv(max_steps=3)
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(18))
    env.reset(seed=0)
    flags = [env.step(np.full(18, 0.05))[2:4] for _ in range(3)]
    assert flags == [(False, False), (False, False), (False, True)]
    with pytest.raises(RuntimeError, match="reset"):
        env.step(np.zeros(18))


def test_a_failed_simulation_ends_the_episode(env, caplog):
    env.reset(seed=0)
    good, *_ = env.step(np.full(18, 0.1))
    env.osim_model.getCoordinateSet().get("knee_angle_r").setSpeedValue(env.state, math.nan)
    obs, reward, terminated, truncated, info = env.step(np.zeros(18))
    assert terminated and not truncated and info["diverged"] and reward == 0.0
    assert np.array_equal(obs, good), "the episode ends on the last state OpenSim computed"
    assert "failed" in caplog.text
    env.reset(seed=0)
    assert "diverged" not in env.step(np.zeros(18))[4]


def test_bad_actions_raise_clear_errors_and_excitations_are_clipped(env):
    env.reset(seed=0)
    for bad in (np.full(18, np.nan), np.r_[np.zeros(17), np.inf]):
        with pytest.raises(ValueError, match="NaN or inf"):
            env.step(bad)
    for shape in ((17,), (1, 18), ()):
        with pytest.raises(ValueError, match="shape"):
            env.step(np.zeros(shape))
    raw = np.linspace(-2.0, 3.0, 18)
    clipped = RunOpenSimEnv()
    clipped.reset(seed=0)
    env.reset(seed=0)
    for _ in range(3):
        assert np.array_equal(env.step(raw)[0], clipped.step(np.clip(raw, 0, 1))[0])
    with pytest.raises(ValueError, match="difficulty"):
        RunOpenSimEnv(difficulty=3)
    with pytest.raises(ValueError, match="left_psoas"):
        RunOpenSimEnv(left_psoas="psoas")


def test_each_excitation_drives_its_own_muscle(env):
    for muscle in (0, 11, 17):
        env.reset(seed=0)
        excitation = np.zeros(18)
        excitation[muscle] = 1.0
        for _ in range(3):
            *_, info = env.step(excitation)
        activation = info["muscle_activation"]
        assert np.argmax(activation) == muscle and np.sort(activation)[-2] < 0.05


# ------------------------------------------------------------------------------ difficulty


def test_difficulty_two_scales_the_psoas_max_force():
    def max_force(env):
        muscles = env.osim_model.getMuscles()
        return np.array([muscles.get(n).getMaxIsometricForce() for n in env.muscle_names])

    flat = RunOpenSimEnv()
    _, flat_info = flat.reset(seed=0)
    base = max_force(flat)
    env = RunOpenSimEnv(difficulty=2)
    obs, info = env.reset(seed=7)
    left, right = env.psoas
    assert left != 1.0 and right != 1.0
    np.testing.assert_allclose(obs[36:38], env.psoas, rtol=1e-6)
    scale = np.ones(18)
    scale[env.muscle_names.index("iliopsoas_r")] = right
    scale[env.muscle_names.index("glut_max_l")] = left  # the 2017 code's index 11
    np.testing.assert_allclose(max_force(env), base * scale)
    # Fibres in equilibrium scale with the strength: the force is in effect, not only stored.
    np.testing.assert_allclose(info["muscle_force"], flat_info["muscle_force"] * scale, rtol=1e-9)

    fixed = RunOpenSimEnv(difficulty=2, left_psoas="iliopsoas_l")
    fixed.reset(seed=7)
    assert fixed.psoas == env.psoas
    scale[11], scale[12] = 1.0, left
    np.testing.assert_allclose(max_force(fixed), base * scale)

    obs, _ = env.reset(seed=7, options={"difficulty": 0})  # strengths restored, no obstacles
    np.testing.assert_allclose(max_force(env), base)
    assert env.obstacles == [] and tuple(obs[38:]) == NO_OBSTACLE


def test_obstacles_are_placed_and_push_the_feet(monkeypatch):
    env = RunOpenSimEnv(difficulty=1)
    obs, _ = env.reset(seed=3)
    geometry = env.osim_model.getContactGeometrySet()
    for i, (x, y, r) in enumerate(env.obstacles):
        sphere = geometry.get(f"obstacle_{i}")
        np.testing.assert_allclose(sphere.get_location().to_numpy(), [x, y, 0.0])
        assert opensim.ContactSphere.safeDownCast(sphere).getRadius() == r
    np.testing.assert_allclose(obs[38:], env.obstacles[0], rtol=1e-6)  # pelvis x is 0 at reset

    _, flat = env.reset(seed=3, options={"difficulty": 0})
    heel = flat["body_pos"][env.body_names.index("calcn_r")]
    # An obstacle where the heels are (the spheres lie at z = 0, between the feet, as in 2017).
    monkeypatch.setattr(l2r.sim.env, "draw_episode", lambda rng, difficulty: ([(heel[0] + 0.03, 0.0, 0.1)], (1.0, 1.0)))
    _, info = env.reset(seed=3)
    assert geometry.get("obstacle_0").get_location().get(0) == heel[0] + 0.03
    pushed = info["contact_force"] - flat["contact_force"]
    assert pushed[0, 1] > 100 and pushed[2, 1] > 100, "both heels rest on the obstacle"
    assert not pushed[[1, 3]].any(), "the toes do not reach it"
    np.testing.assert_allclose(info["contact_force"].sum(0), newton(env), rtol=1e-9, atol=1e-6)


# ------------------------------------------------------------------------------ info, loggers


def test_info_has_run_v0s_layout_and_opensims_values(env):
    mujoco_env = gymnasium.make("l2r/Run-v0").unwrapped
    _, mujoco_info = mujoco_env.reset(seed=0)
    _, info = env.reset(seed=0)
    assert env.body_names == mujoco_env.body_names
    assert env.muscle_names == mujoco_env.muscle_names and env.ligament_names == LIGAMENTS
    assert set(mujoco_info) <= set(info) and "fiber_length" in info
    for key, value in mujoco_info.items():
        assert np.shape(info[key]) == np.shape(value), key
    np.testing.assert_allclose(info["body_pos"], mujoco_info["body_pos"], rtol=0, atol=1e-6)
    np.testing.assert_allclose(info["body_quat"], mujoco_info["body_quat"], rtol=0, atol=1e-9)
    np.testing.assert_allclose(info["muscle_activation"], 0.05)
    muscles = [env.osim_model.getMuscles().get(n) for n in env.muscle_names]
    np.testing.assert_allclose(info["fiber_length"], [m.getFiberLength(env.state) for m in muscles])
    assert np.all(info["muscle_length"] > info["fiber_length"]) and np.all(info["muscle_force"] > 0)

    # The contact forces are the forces on the feet: with gravity they move the centre of mass.
    assert info["contact_force"][:, 1].sum() > 1.5 * 9.8 * 79  # the feet start in the ground
    np.testing.assert_allclose(info["contact_force"].sum(0), newton(env), rtol=1e-9, atol=1e-6)
    for _ in range(20):
        *_, info = env.step(np.full(18, 0.3))
        np.testing.assert_allclose(info["contact_force"].sum(0), newton(env), rtol=1e-9, atol=1e-6)


def test_missing_opensim_is_one_clear_error():
    hide = "import sys; sys.modules['opensim'] = None\n"
    code = hide + "import gymnasium, l2r.sim, l2r.sim.opensim_env\ngymnasium.make('l2r/RunOpenSim-v0')"
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=SUBPROCESS_ENV,
                            timeout=120)
    assert result.returncode == 1
    assert result.stderr.strip().splitlines()[-1] == f"ImportError: {opensim_env.MISSING_OPENSIM}"
    assert "pip install 'l2r[opensim]'" in opensim_env.MISSING_OPENSIM


# ------------------------------------------------------------------------------ commands


@pytest.mark.slow
def test_eval_runs_a_checkpoint_on_opensim(tmp_path):
    config = SACConfig(hidden=(16, 16), precision="float32")
    checkpoint = save_checkpoint(tmp_path / "checkpoint.pt", init_state(config, 41, 18, seed=0), config, 41, 18)
    result = subprocess.run(
        [sys.executable, "-m", "l2r.cli", "eval", str(checkpoint), "--env-id", "l2r/RunOpenSim-v0",
         "--episodes", "1", "--json", "--progress-every", "0.5"],
        cwd=ROOT, capture_output=True, text=True, env=SUBPROCESS_ENV, timeout=300)  # fmt: skip
    assert result.returncode == 0, result.stderr[-3000:]
    out = json.loads(result.stdout)
    assert out["env_id"] == "l2r/RunOpenSim-v0" and len(out["distances"]) == 1
    assert 0 < out["lengths"][0] <= MAX_STEPS and math.isfinite(out["distances"][0])
    assert "l2r eval: 0 of 1 episodes done" in result.stderr


@pytest.mark.slow
def test_an_opensim_actor_logs_episodes_that_replay_exactly(tmp_path):
    run, port = f"osim{uuid.uuid4().hex[:8]}", free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    with zenoh.open(session_config(listen=[endpoint])) as session:
        # The actor steps only while a replay shard is alive: this test plays that part.
        token = session.liveliness().declare_token(Keys(run).alive("replay", 0))
        result = subprocess.run(
            [sys.executable, "-m", "l2r.actors", "--run", run, "--connect", endpoint, "--env-id", "l2r/RunOpenSim-v0",
             "--num-envs", "2", "--max-steps", "120", "--episode-log-dir", str(tmp_path), "--log-every", "1"],
            cwd=ROOT, capture_output=True, text=True, timeout=300, env=SUBPROCESS_ENV)  # fmt: skip
        token.undeclare()
    assert result.returncode == 0, result.stderr[-3000:]
    assert "l2r/RunOpenSim-v0" in result.stderr

    files = sorted(tmp_path.glob("*.mcap"))
    assert files, "random excitations fall within 60 actions of 0.03 s"
    env = ActionRepeat(gymnasium.make("l2r/RunOpenSim-v0"), 3)
    for path in files:
        episode = read_episode(path)
        assert episode.episode["env_id"] == "l2r/RunOpenSim-v0"
        steps = episode.steps
        obs, info = env.reset(seed=int(episode.episode["seed"]))
        for k, action in enumerate(steps["action"]):
            obs, reward, terminated, truncated, info = env.step(action)
            assert np.array_equal(steps["observation"][k], obs) and steps["reward"][k] == reward
            assert np.array_equal(steps["contact_force"][k], info["contact_force"].ravel())
            assert np.array_equal(episode.pos[k], info["body_pos"][1:])
        assert terminated or truncated


def test_the_commands_offer_the_opensim_env():
    for parser in (actor_parser(), eval_parser()):
        assert "l2r/RunOpenSim-v0" in " ".join(parser.format_help().split())
