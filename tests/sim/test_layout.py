"""The observation and action names the learner uses match what the environment produces."""

import gymnasium
import numpy as np

import l2r.sim  # noqa: F401  (registers the envs)
from l2r.sim import layout


def test_the_layout_names_the_env_s_muscles_and_its_world_x_coordinates():
    env = gymnasium.make("l2r/Run-v0").unwrapped
    assert env.muscle_names == layout.ACTION_LABELS
    obs, _ = env.reset(seed=0)
    assert obs.shape == (layout.OBS_SIZE,)
    # Reset: pelvis at x = 0, the tracked bodies' x are small offsets from it.
    assert obs[layout.PELVIS_X] == 0 and all(abs(obs[i]) < 0.2 for i in layout.WORLD_X)


def test_mirrored_excitations_give_the_mirrored_run():
    """The body is left-right symmetric and starts symmetric, so driving it with every action's legs
    swapped must give every observation with its legs swapped: what `--mirror` trains on is real."""
    env = gymnasium.make("l2r/Run-v0")
    first, _ = env.reset(seed=0)
    assert np.array_equal(first, first[layout.MIRROR_OBS])
    actions = np.random.default_rng(0).random((60, len(layout.ACTION_LABELS)))
    runs = []
    for order in (slice(None), layout.MIRROR_ACTION):
        env.reset(seed=0)
        runs.append(np.array([env.step(a[order])[:2] for a in actions], dtype=object))
    straight, mirrored = runs
    obs = np.stack(straight[:, 0]), np.stack(mirrored[:, 0])
    assert np.abs(obs[0] - obs[0][:, layout.MIRROR_OBS]).max() > 0.01  # the run itself is not symmetric
    np.testing.assert_allclose(obs[1], obs[0][:, layout.MIRROR_OBS], atol=1e-5)
    np.testing.assert_allclose(mirrored[:, 1].astype(float), straight[:, 1].astype(float), atol=1e-7)
