"""What the networks see: pelvis-relative x, running standardisation, mirrored transitions."""

import numpy as np
import pytest
import torch

from l2r.learner.checkpoint import load_checkpoint, save_checkpoint
from l2r.learner.sac import SACConfig, batch_from_numpy, init_state, prepare, update
from l2r.policy import act, build_policy, check_spec, load_policy_state, policy_state
from l2r.sim import layout

OBS, ACT = layout.OBS_SIZE, len(layout.ACTION_LABELS)


def config(**options) -> SACConfig:
    return SACConfig(hidden=(32, 32), batch_size=64, precision="float32", **options)


def random_batch(n: int = 64, seed: int = 0):
    rng = np.random.default_rng(seed)
    obs = rng.normal(size=(n, OBS)) * np.linspace(0.1, 20, OBS) + np.linspace(-5, 5, OBS)
    return batch_from_numpy(obs, rng.random((n, ACT)), rng.normal(size=n), obs + rng.normal(size=(n, OBS)),
                            np.zeros(n))


def test_relative_x_measures_world_x_from_the_pelvis_and_leaves_the_rest():
    state = init_state(config(relative_x=True), OBS, ACT, seed=0)
    obs = torch.arange(OBS, dtype=torch.float32).reshape(1, OBS) + 100.0
    seen = state.actor.observation_filter(obs)[0]
    moved = [layout.PELVIS_X, *layout.WORLD_X]
    pelvis_x = obs[0, layout.PELVIS_X]
    assert torch.equal(seen[moved], obs[0, moved] - pelvis_x)
    assert seen[layout.OBS_LABELS.index("com.x")] == obs[0, layout.OBS_LABELS.index("com.x")] - pelvis_x
    kept = [i for i in range(OBS) if i not in moved]
    assert torch.equal(seen[kept], obs[0, kept])
    assert layout.OBS_LABELS.index("obstacle.dx") in kept  # already relative


def test_normalisation_statistics_are_those_of_every_batch_seen():
    state = init_state(config(normalize_obs=True), OBS, ACT, seed=0)
    batches = [random_batch(n, seed) for n, seed in ((64, 1), (10, 2), (300, 3))]
    for batch in batches:
        prepare(state, batch, config(normalize_obs=True))
    everything = np.concatenate([b.obs.numpy() for b in batches]).astype(np.float64)
    f = state.actor.observation_filter
    assert f.count.item() == len(everything)
    np.testing.assert_allclose(f.mean.numpy(), everything.mean(0), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(f.var.numpy(), everything.var(0), rtol=1e-9, atol=1e-9)
    seen = f(batches[2].obs)
    assert seen.abs().max() <= f.CLIP and abs(seen.mean().item()) < 0.2 and 0.6 < seen.std().item() < 1.2


def test_the_statistics_travel_with_the_weights_and_the_checkpoint(tmp_path):
    sac = config(relative_x=True, normalize_obs=True)
    state = init_state(sac, OBS, ACT, seed=0)
    batch = prepare(state, random_batch(), sac)
    update(state, batch, sac)
    obs = random_batch(8, seed=5).obs.numpy()
    expected = act(state.actor, obs, deterministic=True)

    # An actor: the spec and the published arrays rebuild the same policy, statistics included.
    actor_policy = build_policy(check_spec(state.actor.spec))
    load_policy_state(actor_policy, policy_state(state.actor))
    np.testing.assert_allclose(act(actor_policy, obs, deterministic=True), expected, atol=1e-6)
    untrained = build_policy(check_spec(state.actor.spec))
    untrained.load_state_dict({**state.actor.state_dict(),
                               **{k: v for k, v in untrained.state_dict().items() if "filter" in k}})
    assert not np.allclose(act(untrained, obs, deterministic=True), expected, atol=1e-3)

    # l2r eval: the checkpoint's policy.
    save_checkpoint(tmp_path / "learner/checkpoint.pt", state, sac, OBS, ACT)
    np.testing.assert_allclose(act(load_checkpoint(tmp_path).policy(), obs, deterministic=True), expected,
                               atol=1e-6)


def test_a_spec_from_before_the_options_means_raw_observations():
    old = {"obs_dim": OBS, "act_dim": ACT, "hidden": [8], "activation": "elu", "layer_norm": True}
    spec = check_spec(old)
    assert spec["relative_x"] is False and spec["normalize_obs"] is False
    assert set(policy_state(build_policy(spec))) == set(policy_state(build_policy(old)))
    with pytest.raises(ValueError, match="relative_x"):
        check_spec(old | {"obs_dim": 40, "relative_x": True})


def test_mirroring_swaps_the_legs_of_about_half_the_batch_and_nothing_else():
    torch.manual_seed(0)
    sac = config(mirror=True)
    state = init_state(sac, OBS, ACT, seed=0)
    batch = random_batch(2000)
    mirrored = prepare(state, batch, sac)
    swapped = (mirrored.obs != batch.obs).any(1)
    assert 0.45 < swapped.float().mean() < 0.55
    for new, old, order in ((mirrored.obs, batch.obs, layout.MIRROR_OBS),
                            (mirrored.next_obs, batch.next_obs, layout.MIRROR_OBS),
                            (mirrored.action, batch.action, layout.MIRROR_ACTION)):
        assert torch.equal(new[swapped], old[swapped][:, order])
        assert torch.equal(new[~swapped], old[~swapped])
    assert torch.equal(mirrored.reward, batch.reward) and torch.equal(mirrored.terminated, batch.terminated)
    with pytest.raises(ValueError, match="mirror needs"):
        init_state(sac, 5, 3)


def test_the_mirror_swaps_right_and_left_names():
    obs = dict(zip(layout.OBS_LABELS, np.array(layout.OBS_LABELS)[layout.MIRROR_OBS]))
    assert obs["hip_flexion_r"] == "hip_flexion_l" and obs["toes_l.y"] == "toes_r.y"
    assert obs["psoas_r"] == "psoas_l" and obs["pelvis_tx"] == "pelvis_tx" and obs["com.vx"] == "com.vx"
    actions = dict(zip(layout.ACTION_LABELS, np.array(layout.ACTION_LABELS)[layout.MIRROR_ACTION]))
    assert actions["glut_max_r"] == "glut_max_l" and actions["tib_ant_l"] == "tib_ant_r"
