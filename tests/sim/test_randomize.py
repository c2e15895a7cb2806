"""Per-episode randomisation of RunEnv's body, and the noise wrappers: what each draw changes, its
bounds, its seed, and that everything off is the env of 2017."""

import dataclasses

import numpy as np
import pytest

from l2r.sim import thelen
from l2r.sim.env import RunEnv
from l2r.sim.model import OSIM_PATH
from l2r.sim.opensim import read_osim
from l2r.sim.randomize import Randomization
from l2r.sim.wrappers import ActionNoise, ObservationNoise

FRACTIONS = dict(strength=0.1, tendon_slack=0.03, fiber_length=0.04, mass=0.2, contact_stiffness=0.3,
                 contact_damping=0.25, friction=0.15)


@pytest.fixture(scope="module")
def plain():
    return RunEnv()


@pytest.fixture(scope="module")
def randomized():
    return RunEnv(randomize=FRACTIONS)


def rollout(env, seed, steps=30):
    """The first observation, then observation and reward of each step, as one array."""
    obs, _ = env.reset(seed=seed)
    out = [obs.astype(np.float64)]
    for a in np.random.default_rng(seed).uniform(0.0, 1.0, (steps, 18)):
        obs, reward, terminated, truncated, _ = env.step(a)
        out.append(np.append(obs, reward))
        if terminated or truncated:
            break
    return np.concatenate(out)


def body_of(env):
    """What randomisation may change: muscle table, masses, inertias, subtree masses, contact law."""
    m = env.model
    return (env._physics.params.copy(), m.body_mass.copy(), m.body_inertia.copy(), m.body_subtreemass.copy(),
            env._physics.contact.copy())


def test_off_is_the_env_without_randomisation(plain):
    """All zero is the default env, whose step holds the excitations over all its physics steps
    and whose body stays the compiled model's."""
    zero = RunEnv(randomize={name: 0.0 for name in Randomization.names()})
    assert not zero.randomize
    assert np.array_equal(rollout(plain, 3), rollout(zero, 3))  # bit for bit
    zero.reset(seed=3)
    plain.reset(seed=3)
    for a in np.random.default_rng(3).uniform(0.0, 1.0, (10, 18)):
        zero.step(a)
        plain._physics.excitation[:] = a
        plain._physics.step(plain.substeps)
        assert np.array_equal(zero.data.qpos, plain.data.qpos) and np.array_equal(zero.data.qvel, plain.data.qvel)
    _, info = zero.reset(seed=4)
    assert "randomization" not in info and zero.randomized == {}
    defaults = body_of(RunEnv())
    for env in (plain, zero):
        env.reset(seed=5)
        for now, default in zip(body_of(env), defaults):
            assert np.array_equal(now, default)


def test_each_draw_scales_what_it_names_within_its_bounds(plain, randomized):
    plain.reset(seed=0)
    table, mass, inertia, _, contact = body_of(plain)
    seen = []
    for seed in range(3):
        _, info = randomized.reset(seed=seed)
        drawn = info["randomization"]
        assert set(drawn) == set(FRACTIONS)
        for name, fraction in FRACTIONS.items():
            factor = np.asarray(drawn[name])
            assert np.all(np.abs(factor - 1.0) <= fraction) and np.any(factor != 1.0), name
        now, now_mass, now_inertia, now_subtree, now_contact = body_of(randomized)
        np.testing.assert_allclose(now[:, thelen.MAX_FORCE], table[:, thelen.MAX_FORCE] * drawn["strength"], rtol=1e-14)
        np.testing.assert_allclose(now[:, thelen.SLACK_LENGTH], table[:, thelen.SLACK_LENGTH] * drawn["tendon_slack"],
                                   rtol=1e-14)
        np.testing.assert_allclose(now[:, thelen.OPTIMAL_LENGTH],
                                   table[:, thelen.OPTIMAL_LENGTH] * drawn["fiber_length"], rtol=1e-14)
        np.testing.assert_allclose(now_mass[1:], mass[1:] * drawn["mass"], rtol=1e-14)
        np.testing.assert_allclose(now_inertia[1:], inertia[1:] * drawn["mass"][:, None], rtol=1e-14)
        assert now_subtree[0] == pytest.approx(now_mass.sum(), rel=1e-14)
        assert now_subtree[0] != pytest.approx(mass.sum(), rel=1e-6)
        # [Hertz constant (stiffness^(2/3) / 2), dissipation, static, dynamic, viscous friction, transition speed]
        scale = [drawn["contact_stiffness"] ** (2 / 3), drawn["contact_damping"]] + [drawn["friction"]] * 3 + [1.0]
        np.testing.assert_allclose(now_contact, contact * scale, rtol=1e-14)
        seen.append(drawn["strength"])
    assert not np.array_equal(seen[0], seen[1])  # episodes differ


def test_scaled_muscles_are_the_muscles_of_the_scaled_values():
    muscles = read_osim(OSIM_PATH).muscles
    rng = np.random.default_rng(0)
    force, fiber, slack = (rng.uniform(0.9, 1.1, len(muscles)) for _ in range(3))
    table = thelen.muscle_parameters(muscles)
    thelen.scale_muscles(table, force, fiber, slack)
    scaled = [dataclasses.replace(m, max_force=m.max_force * f, optimal_length=m.optimal_length * o,
                                  slack_length=m.slack_length * s)
              for m, f, o, s in zip(muscles, force, fiber, slack)]
    np.testing.assert_allclose(table, thelen.muscle_parameters(scaled), rtol=1e-13)


def test_draws_and_first_steps_repeat_with_the_seed(randomized):
    a = rollout(randomized, 7, steps=5), randomized.randomized
    b = rollout(randomized, 7, steps=5), randomized.randomized
    c = rollout(randomized, 8, steps=5), randomized.randomized
    assert np.array_equal(a[0], b[0]) and not np.array_equal(a[0], c[0])
    for name in FRACTIONS:
        assert np.array_equal(a[1][name], b[1][name]) and not np.array_equal(a[1][name], c[1][name])


def test_a_seed_gives_the_same_course_with_or_without_randomisation():
    plain, randomized = RunEnv(difficulty=2), RunEnv(difficulty=2, randomize={"mass": 0.1, "delay": 0.5})
    for seed in range(3):
        plain.reset(seed=seed)
        randomized.reset(seed=seed)
        assert plain.obstacles == randomized.obstacles and plain.psoas == randomized.psoas


def test_the_delay_holds_the_last_excitations_for_exactly_one_physics_step(plain):
    """A delayed env step of a: one physics step of the last excitations, then a for the rest.
    The reference takes single physics steps as env steps of its own."""
    delayed = RunEnv(randomize={"delay": 1.0})
    _, info = delayed.reset(seed=0)
    assert info["randomization"] == {"delay": True}
    plain.reset(seed=0)
    plain.substeps = 1
    try:
        last = np.zeros(18)  # what a reset leaves held
        for a in np.random.default_rng(1).uniform(0.0, 1.0, (5, 18)):
            delayed.step(a)
            for excitation in [last] + [a] * (delayed.substeps - 1):
                plain.step(excitation)
            last = a
            assert np.array_equal(delayed.data.qpos, plain.data.qpos)
            assert np.array_equal(delayed.data.qvel, plain.data.qvel)
    finally:
        plain.substeps = delayed.substeps


def test_the_delay_is_drawn_with_its_probability():
    rng = np.random.default_rng(0)
    delays = [Randomization(delay=0.3).draw(rng, 18, 13)["delay"] for _ in range(400)]
    assert 0.3 - 0.08 < np.mean(delays) < 0.3 + 0.08
    assert {"delay": True} == Randomization(delay=1.0).draw(rng, 18, 13)
    assert {} == Randomization().draw(rng, 18, 13)


@pytest.mark.parametrize("value, message", [
    ({"strenght": 0.1}, "has no strenght"),
    ({"mass": -0.1}, "from 0 to 0.5"),
    ({"mass": 0.6}, "from 0 to 0.5"),
    ({"delay": 1.5}, "probability from 0 to 1"),
    ({"friction": float("nan")}, "must be a number"),
    ({"friction": "0.1"}, "must be a number"),
    ([0.1], "takes a mapping"),
])
def test_bad_randomisation_is_a_clear_error(value, message):
    with pytest.raises(ValueError, match=message):
        Randomization.of(value)


def test_the_command_line_form():
    assert Randomization.parse("strength=0.05, delay=1") == Randomization(strength=0.05, delay=1.0)
    assert not Randomization.parse("")
    assert str(Randomization(mass=0.1, delay=0.5)) == "mass=0.1,delay=0.5" and str(Randomization()) == ""
    recipe = "strength=0.05,tendon_slack=0.02,fiber_length=0.02,mass=0.05,contact_stiffness=0.2,friction=0.2,delay=0.5"
    assert str(Randomization.parse(recipe)) == recipe
    for text in ("strength", "strength=x", "mass=0.1,,speed=2"):
        with pytest.raises(ValueError):
            Randomization.parse(text)


# -- noise -----------------------------------------------------------------------------------------

def test_observation_noise_has_its_std_and_repeats_with_the_seed(plain):
    noisy = ObservationNoise(plain, std=0.02)
    noise = []
    for seed in range(12):
        clean, _ = plain.reset(seed=seed)
        seen, _ = noisy.reset(seed=seed)
        noise.append(seen.astype(np.float64) - clean)
    noise = np.concatenate(noise)  # 492 draws
    assert abs(noise.mean()) < 4 * 0.02 / np.sqrt(noise.size)
    assert 0.9 < noise.std() / 0.02 < 1.1
    again, _ = noisy.reset(seed=0)
    assert np.array_equal(again - plain.reset(seed=0)[0], noise[:41].astype(np.float32))


def test_action_noise_has_its_std_and_repeats_with_the_seed(plain):
    noisy = ActionNoise(plain, std=0.05)
    held = []
    for _ in range(2):
        noisy.reset(seed=3)
        held.append([])
        for _ in range(20):
            noisy.step(np.full(18, 0.5))
            held[-1].append(plain.excitation - 0.5)
    noise = np.array(held[0]).ravel()  # 360 draws, none near the clip at 0 or 1
    assert np.array_equal(held[0], held[1])
    assert abs(noise.mean()) < 4 * 0.05 / np.sqrt(noise.size)
    assert 0.9 < noise.std() / 0.05 < 1.1


def test_noise_std_must_be_a_number_not_below_zero(plain):
    for wrapper in (ObservationNoise, ActionNoise):
        with pytest.raises(ValueError, match="std"):
            wrapper(plain, std=-0.1)
