"""`l2r/RunWarp-v0` (MuJoCo Warp, float32, Warp's CPU device here) against `l2r/Run-v0` (numba,
float64) driven by the same excitations from the same reset, on flat ground and with obstacles.

Cost: the first MuJoCo Warp step compiles its kernels, about 4 minutes on a 2-core CPU with an
empty Warp kernel cache (~/.cache/warp), under a second with a warm one.
"""

from __future__ import annotations

import gymnasium
import numpy as np
import pytest
import warp as wp

import l2r.sim  # noqa: F401  (registers the environments)
from l2r.sim import env as port_env
from l2r.sim import model as body
from l2r.sim.layout import JOINTS, OBS_LABELS
from l2r.sim.warp import env as warp_env

STEPS = 20  # 0.2 s
ANGLES = [OBS_LABELS.index(c) for c in ("pelvis_tilt", *JOINTS)]
PELVIS = [OBS_LABELS.index(c) for c in ("pelvis_tx", "pelvis_ty")]


def test_warp_worlds_follow_the_numba_port():
    """Two worlds, one driven as the numba env is and one held at zero excitation: the first
    follows the numba env's joints within 0.01 degrees and its pelvis within 0.01 cm over 0.2 s
    (float32 against float64), the second does not move with it, and both start their next
    episode in the step their last one ended (max_steps 20)."""
    actions = np.random.default_rng(0).uniform(0.0, 1.0, (STEPS, 18))
    port = gymnasium.make("l2r/Run-v0", max_steps=STEPS).unwrapped
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=2, max_steps=STEPS, device="cpu")
    obs, info = port.reset(seed=0)
    got, got_info = worlds.reset(seed=0)
    np.testing.assert_allclose(got[0], obs, atol=1e-5)
    np.testing.assert_allclose(got_info["muscle_force"][0], info["muscle_force"], rtol=1e-4, atol=0.01)
    first, first_distance = got.copy(), got_info["distance"].copy()
    for k, a in enumerate(actions):
        obs, reward, terminated, truncated, info = port.step(a)
        got, got_reward, got_terminated, got_truncated, got_info = worlds.step(np.stack([a, np.zeros(18)]))
        last = got_info["final_obs"] if k == STEPS - 1 else got
        assert np.degrees(np.abs(last[0, ANGLES] - obs[ANGLES])).max() < 0.01
        assert 100 * np.abs(last[0, PELVIS] - obs[PELVIS]).max() < 0.01
        assert abs(got_reward[0] - reward) < 1e-5
        assert got_terminated[0] == terminated and got_truncated[0] == truncated
    assert np.degrees(np.abs(last[1, ANGLES] - obs[ANGLES])).max() > 1.0  # the idle world went its own way
    assert got_truncated.all()
    np.testing.assert_allclose(got, first, atol=1e-6)  # both reset in the step they ended
    np.testing.assert_allclose(got_info["distance"], first_distance)  # and report their new episode's info


RANDOMIZE = {"strength": 0.2, "tendon_slack": 0.05, "fiber_length": 0.05, "mass": 0.2, "contact_stiffness": 0.3,
             "contact_damping": 0.3, "friction": 0.3, "delay": 1.0}


@pytest.mark.parametrize("difficulty", [0, 2])
def test_randomised_warp_worlds_are_the_randomised_port_s_bodies(difficulty):
    """Every randomisation at once (every episode delayed): world 0 draws the port's body from
    the same seed, after the same course (muscles, masses, contact law, delay) and follows the
    port within 0.01 degrees and 0.01 cm over 0.2 s; world 1, its own body from another seed,
    does not."""
    actions = np.random.default_rng(1).uniform(0.0, 1.0, (STEPS, 18))
    port = gymnasium.make("l2r/Run-v0", difficulty=difficulty, randomize=RANDOMIZE).unwrapped
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=2, difficulty=difficulty, device="cpu", randomize=RANDOMIZE)
    obs, info = port.reset(seed=3)
    got, _ = worlds.reset(seed=[3, 4])
    drawn = worlds.unwrapped.randomized
    assert drawn[0].keys() == info["randomization"].keys() == RANDOMIZE.keys() and drawn[0]["delay"]
    for name, value in info["randomization"].items():
        np.testing.assert_array_equal(drawn[0][name], value)
        assert not np.array_equal(drawn[1][name], value) or name == "delay"
    np.testing.assert_allclose(worlds.unwrapped.max_isometric_force[0], port.max_isometric_force, rtol=1e-6)
    np.testing.assert_allclose(got[0], obs, atol=1e-5)
    for a in actions:
        obs, *_ = port.step(a)
        got, *_ = worlds.step(np.stack([a, a]))
        assert np.degrees(np.abs(got[0, ANGLES] - obs[ANGLES])).max() < 0.01
        assert 100 * np.abs(got[0, PELVIS] - obs[PELVIS]).max() < 0.01
    assert np.degrees(np.abs(got[1, ANGLES] - obs[ANGLES])).max() > 1.0
    one = gymnasium.make("l2r/RunWarp-v0", device="cpu", randomize={"strength": 0.1})
    assert set(one.reset(seed=3)[1]["randomization"]) == {"strength"}


def test_warp_worlds_draw_the_ports_obstacles_and_psoas_strengths():
    """At difficulty 2 world w's episodes are the port's from seed + w: the same obstacles (the
    observation's last 3 values, and the spheres where the port puts them) and psoas strengths
    (observation values 36-37, max forces scaled alike, left_psoas honoured), in the first
    episode and the one the same-step reset begins."""
    port = gymnasium.make("l2r/Run-v0", difficulty=2, left_psoas="iliopsoas_l").unwrapped
    obstacle_geoms = [port.model.geom(g).id for g in body.OBSTACLES]

    def port_episodes(seed: int) -> list[tuple]:
        """Observation values 36-40, obstacle places and max forces of the port's first two
        episodes from `seed`."""
        return [(port.reset(seed=s)[0][36:], port.model.geom_pos[obstacle_geoms].copy(), port.max_isometric_force)
                for s in (seed, None)]

    expected = [port_episodes(7 + w) for w in range(3)]
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=3, difficulty=2, left_psoas="iliopsoas_l",
                                max_steps=1, device="cpu")
    got, _ = worlds.reset(seed=7)
    for episode in range(2):
        geom_pos = worlds.unwrapped._physics.model.geom_pos.numpy()[:, obstacle_geoms]
        forces = worlds.unwrapped.max_isometric_force
        for w in range(3):
            obs, places, max_force = expected[w][episode]
            np.testing.assert_allclose(got[w, 36:], obs, atol=1e-6)
            np.testing.assert_allclose(geom_pos[w], places, atol=1e-6)
            np.testing.assert_allclose(forces[w], max_force, rtol=1e-6)
        assert len({tuple(o) for o in got[:, 36:]}) == 3  # each world drew its own
        got = worlds.step(np.zeros((3, 18)))[0]  # every world truncated and began its next episode


def test_warp_worlds_meet_an_obstacle_as_the_port_does(monkeypatch):
    """A sphere just ahead of the toes (no seed draws one within the feet's reach so soon: every
    drawn obstacle's centre lies at x >= 1 m): random excitation presses a toe on it from the second
    step to the fourth and takes it off; over 0.1 s the joints stay within 0.01 degrees and the
    pelvis within 0.01 cm of the port's, the obstacle's forces on the feet within 0.1 N of the
    port's (up to 200 N; the same law in float32 against float64)."""
    course = [(0.158, 0.02, 0.1), (4.0, 0.0, 0.05), (4.5, 0.0, 0.05)]
    for backend in (port_env, warp_env):
        monkeypatch.setattr(backend, "draw_episode", lambda rng, difficulty: (course, (1.0, 1.0)))
    port = gymnasium.make("l2r/Run-v0", difficulty=1).unwrapped
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=1, difficulty=1, device="cpu")
    port.reset(seed=0)
    worlds.reset(seed=0)
    pressed = []
    for a in np.random.default_rng(0).uniform(0.0, 1.0, (10, 18)):
        obs, _, _, _, info = port.step(a)
        got, _, _, _, got_info = worlds.step(a[None])
        assert np.degrees(np.abs(got[0, ANGLES] - obs[ANGLES])).max() < 0.01
        assert 100 * np.abs(got[0, PELVIS] - obs[PELVIS]).max() < 0.01
        np.testing.assert_allclose(got[0, 38:], obs[38:], atol=1e-5)
        np.testing.assert_allclose(got_info["contact_force"][0], info["contact_force"], atol=0.1)
        pressed.append(np.abs(info["contact_force"][:, 2]).max() > 1.0)  # the ground's forces have no z
    assert pressed[1:4] == [True] * 3 and not any(pressed[4:])  # the toe met the sphere and left it


def test_one_world_env_has_the_single_env_api():
    env = gymnasium.make("l2r/RunWarp-v0", max_steps=2, device="cpu")
    obs, _ = env.reset(seed=0)
    assert obs.shape == (41,) and obs.dtype == np.float32
    obs, reward, terminated, truncated, info = env.step(np.full(18, 0.5))
    assert isinstance(reward, float) and not terminated and not truncated and info["muscle_force"].shape == (18,)
    port = gymnasium.make("l2r/Run-v0").unwrapped
    assert env.unwrapped.body_names == port.body_names and info["body_pos"].shape == (len(port.body_names), 3)
    assert env.step(np.full(18, 0.5))[3]  # truncated at max_steps
    with pytest.raises(RuntimeError):
        env.step(np.full(18, 0.5))
    env.reset()
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(17))


def test_reset_options_change_the_difficulty():
    env = gymnasium.make("l2r/RunWarp-v0", device="cpu")
    port = gymnasium.make("l2r/Run-v0").unwrapped
    obs, _ = env.reset(seed=3, options={"difficulty": 2})
    np.testing.assert_allclose(obs[36:], port.reset(seed=3, options={"difficulty": 2})[0][36:], atol=1e-6)
    obs, _ = env.reset(options={"difficulty": 0})
    np.testing.assert_array_equal(obs[36:], [1.0, 1.0, *port_env.NO_OBSTACLE])
    with pytest.raises(ValueError, match="difficulty"):
        env.reset(options={"difficulty": 3})


def test_graphs_replay_what_the_launches_do(monkeypatch):
    """The captured steps and resets (the default) give the states launching each kernel from
    Python gives, bit for bit: through resets of one world at a time (the graph reads which from
    the same array each time) and a change of difficulty, which puts obstacles in the course the
    graph reads (a sphere under the toes, as above, so that they push)."""
    course = [(0.158, 0.02, 0.1), (4.0, 0.0, 0.05), (4.5, 0.0, 0.05)]
    monkeypatch.setattr(warp_env, "draw_episode", lambda rng, difficulty: (course, (1.0, 1.0)))
    actions = np.random.default_rng(0).uniform(0.0, 1.0, (6, 3, 18))
    runs = []
    for graphs in (True, False):
        worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=3, device="cpu", graphs=graphs)
        physics, states = worlds.unwrapped._physics, []
        for difficulty in (0, 1):
            states.append(worlds.reset(seed=5, options={"difficulty": difficulty})[0])
            for k, a in enumerate(actions):
                states.append(worlds.step(a)[0])
                physics.reset(np.array([k % 3]))
                states.append(physics.data.qpos.numpy())
        runs.append(states)
        worlds.close()
    for graphed, launched in zip(*runs):
        assert np.isfinite(graphed).all()
        np.testing.assert_array_equal(graphed, launched)


def test_a_device_that_cannot_capture_launches_the_kernels(monkeypatch, caplog):
    """Where capturing a graph fails, the env says so once and steps on launching each kernel."""
    def refuse(*args, **kwargs):
        raise RuntimeError("no graphs here")

    monkeypatch.setattr(wp, "ScopedCapture", refuse)
    actions = np.random.default_rng(2).uniform(0.0, 1.0, (3, 2, 18))
    runs = []
    for graphs in (True, False):
        worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=2, device="cpu", graphs=graphs)
        worlds.reset(seed=1)
        runs.append([worlds.step(a)[0] for a in actions])
        worlds.close()
    np.testing.assert_array_equal(runs[0], runs[1])
    assert [r.message for r in caplog.records if "could not capture" in r.message] == [
        "Warp could not capture the step launches on cpu (no graphs here); launching them one by one"]


def test_disabled_autoreset_resets_the_worlds_asked_with_their_seeds_and_difficulties():
    """With autoreset_mode DISABLED a finished world goes on until a masked reset names it; that
    reset starts it from the pose at rest with the episode `l2r/Run-v0` draws from its seed and
    difficulty, and leaves the other worlds as they were."""
    worlds = gymnasium.make_vec("l2r/RunWarp-v0", num_envs=3, max_steps=2, device="cpu", autoreset_mode="Disabled")
    port = gymnasium.make("l2r/Run-v0").unwrapped
    first, _ = worlds.reset(seed=[10, 11, 12])
    for _ in range(3):
        obs, _, _, truncated, info = worlds.step(np.full((3, 18), 0.5))
    assert truncated.all() and "final_obs" not in info
    assert np.abs(obs[:, :36] - first[:, :36]).max() > 1e-3  # stepped on, not reset
    mask = np.array([False, True, False])
    again, info = worlds.reset(seed=[None, 42, None], options={"reset_mask": mask, "difficulty": 2})
    np.testing.assert_array_equal(again[[0, 2]], obs[[0, 2]])
    np.testing.assert_allclose(again[1, :36], first[1, :36], atol=1e-6)  # the pose at rest
    np.testing.assert_allclose(again[1, 36:], port.reset(seed=42, options={"difficulty": 2})[0][36:], atol=1e-6)
    np.testing.assert_array_equal(worlds.unwrapped.difficulties, [0, 2, 0])
    assert worlds.step(np.full((3, 18), 0.5))[3].tolist() == [True, False, True]
    with pytest.raises(ValueError, match="reset_mask"):
        worlds.reset(options={"reset_mask": np.array([1, 0, 1])})
