"""Image observations in the learner: DrQ's random shift against crops taken by hand, the gather of
a batch's distinct frames into stacks on the device, the encoder's shapes and which loss trains it,
TD3 and SAC updates on image batches, image policies in checkpoints and in `act`, and the vector's
networks and spec as they always were."""

import copy
from dataclasses import replace

import numpy as np
import pytest
import torch

from l2r.config import UsageError
from l2r.encoders import PixelEncoder, random_shift, shift_images, stack_frames
from l2r.learner.__main__ import parse_settings
from l2r.learner.checkpoint import CheckpointError, checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.daemon import LearnerConfig, _check_observations, _initial_state
from l2r.learner import sac
from l2r.learner.sac import batch_from_frames
from l2r.learner.steps import GradientSteps
from l2r.learner.td3 import TD3Config, init_state, update
from l2r.policy import DeterministicPolicy, Policy, act, act_with_log_prob, build_policy, check_spec, default_spec
from l2r.protocol import ObservationSpec, ProtocolError, SampleBatch
from l2r.protocol.observations import FieldSpec

PIXELS = ObservationSpec.parse("pixels: uint8[3, 24, 24]")
CAMERA_AND_STATE = ObservationSpec.parse("pixels: uint8[3, 24, 24], state: float32[4]")
ACT, K = 2, 3


def pixel_config(**overrides) -> TD3Config:
    base = dict(hidden=(16,), batch_size=8, precision="float32", frame_stack=K, augment_pad=2,
                encoder_channels=8, encoder_features=6, policy_delay=1)
    return TD3Config(**(base | overrides))


def sac_config(**overrides) -> sac.SACConfig:
    base = dict(hidden=(16,), batch_size=8, precision="float32", frame_stack=K, augment_pad=2,
                encoder_channels=8, encoder_features=6)
    return sac.SACConfig(**(base | overrides))


def frames_batch(observation: ObservationSpec = PIXELS, n: int = 8, seed: int = 0, act_dim: int = ACT):
    """A batch in the frames form, as a replay shard sends it: 2n distinct frames, stacks of K."""
    rng = np.random.default_rng(seed)
    frames = {name: (rng.integers(0, 256, (2 * n, *f.shape), dtype=np.uint8) if f.dtype == np.uint8
                     else rng.normal(size=(2 * n, *f.shape)).astype(np.float32))
              for name, f in observation.fields.items()}
    rows = rng.integers(0, 2 * n, (2, n, K))
    return batch_from_frames(frames, rows[0], rows[1], rng.random((n, act_dim), dtype=np.float32),
                             rng.normal(size=n).astype(np.float32), np.zeros(n, bool))


def test_a_shift_is_a_crop_of_the_image_padded_with_its_edges():
    images = torch.arange(2 * 1 * 4 * 5, dtype=torch.uint8).reshape(2, 1, 4, 5)
    padded = np.pad(images.numpy(), ((0, 0), (0, 0), (2, 2), (2, 2)), mode="edge")  # pad 2: offsets 0..4
    shifts = torch.tensor([[0, 4], [3, 1]])
    shifted = shift_images(images, shifts, pad=2)
    assert shifted.dtype == torch.uint8 and shifted.shape == images.shape
    np.testing.assert_array_equal(shifted[0], padded[0, :, 0:4, 4:9])
    np.testing.assert_array_equal(shifted[1], padded[1, :, 3:7, 1:6])
    np.testing.assert_array_equal(shift_images(images, torch.full((2, 2), 2), pad=2), images)  # the centre


def test_random_shift_moves_each_image_by_its_own_offset_and_leaves_vectors_alone():
    torch.manual_seed(0)
    images = torch.randint(0, 256, (64, 3, 16, 16), dtype=torch.uint8)
    state = torch.randn(64, 4)
    shifted = random_shift({"pixels": images, "state": state}, ["pixels"], pad=4)
    assert shifted["state"] is state
    # Each shifted image is one of the 81 crops of its own padded image, at offsets drawn apart.
    padded = np.pad(images.numpy(), ((0, 0), (0, 0), (4, 4), (4, 4)), mode="edge")
    offsets = []
    for i, image in enumerate(shifted["pixels"].numpy()):
        crops = [(y, x) for y in range(9) for x in range(9) if np.array_equal(image, padded[i, :, y:y + 16, x:x + 16])]
        assert crops, i
        offsets.append(crops[0])
    assert len(set(offsets)) > 20


def test_frames_are_gathered_into_stacks_oldest_first_along_channels():
    frames = {"pixels": torch.arange(4, dtype=torch.uint8)[:, None, None, None].expand(4, 3, 2, 2),
              "state": torch.arange(4, dtype=torch.float32)[:, None].expand(4, 2)}
    stacks = stack_frames(frames, torch.tensor([[0, 0, 1], [1, 2, 3]]))
    assert stacks["pixels"].shape == (2, 9, 2, 2) and stacks["pixels"].dtype == torch.uint8
    assert stacks["pixels"][1, :, 0, 0].tolist() == [1, 1, 1, 2, 2, 2, 3, 3, 3]
    assert stacks["pixels"][0, :, 1, 1].tolist() == [0, 0, 0, 0, 0, 0, 1, 1, 1]
    assert stacks["state"].tolist() == [[0, 0, 0, 0, 1, 1], [1, 1, 2, 2, 3, 3]]


def test_a_batch_s_frames_go_to_the_device_as_uint8_and_come_out_stacked():
    batch = frames_batch(CAMERA_AND_STATE)
    assert batch.obs["pixels"].shape == (8, 9, 24, 24) and batch.obs["pixels"].dtype == torch.uint8
    assert batch.next_obs["state"].shape == (8, 12) and batch.next_obs["state"].dtype == torch.float32


def test_the_encoder_convolves_stacks_scaled_on_the_device():
    encoder = PixelEncoder(CAMERA_AND_STATE, K, channels=4)
    assert encoder.conv_dim == 4 * 5 * 5 and encoder.vector_dim == 12  # 24 -> 11 -> 9 -> 7 -> 5
    assert encoder.convs["pixels"][0].in_channels == 9 and encoder.convs["pixels"][0].stride == (2, 2)
    pixels = torch.randint(0, 256, (5, 9, 24, 24), dtype=torch.uint8)
    embedding = encoder({"pixels": pixels, "state": torch.ones(5, 12)})
    assert embedding.shape == (5, 112) and torch.equal(embedding[:, 100:], torch.ones(5, 12))
    # 0 ... 255 scaled to -0.5 ... 0.5 before the convolutions
    torch.testing.assert_close(embedding[:, :100], encoder.convs["pixels"](pixels / 255.0 - 0.5))
    embedding_of_84 = PixelEncoder(ObservationSpec.parse("pixels: uint8[3, 84, 84]"), 3)
    assert embedding_of_84.conv_dim == 32 * 35 * 35  # DrQ-v2's 39,200


def test_networks_of_an_image_spec_have_their_own_projections_and_share_one_encoder():
    state = init_state(pixel_config(), CAMERA_AND_STATE, ACT, seed=0)
    assert state.critic.projection is not state.actor.projection
    assert state.target_actor.encoder is state.actor.encoder
    assert state.actor.projection.trunk[0].in_features == 8 * 25 and state.actor.projection.out_dim == 6 + 12
    encoder = set(map(id, state.actor.encoder.parameters()))
    assert encoder <= {id(p) for group in state.critic_opt.param_groups for p in group["params"]}
    assert not encoder & {id(p) for group in state.actor_opt.param_groups for p in group["params"]}


def test_the_critic_loss_trains_the_encoder_and_the_actor_loss_leaves_it_alone():
    config, batch = pixel_config(), frames_batch()
    states = [init_state(config, PIXELS, ACT, seed=1) for _ in range(2)]
    before = states[0].actor.encoder.convs["pixels"][0].weight.detach().clone()
    for state, actor_step in zip(states, (False, True)):
        torch.manual_seed(5)  # the same shifts and noise: the critics' steps are the same
        update(state, batch, config, actor_step)
    critic_only, with_actor = (state.actor.encoder.convs["pixels"][0] for state in states)
    assert critic_only.weight.grad.abs().sum() > 0 and not torch.equal(critic_only.weight, before)
    torch.testing.assert_close(with_actor.weight.grad, critic_only.weight.grad, rtol=0, atol=0)
    assert torch.equal(with_actor.weight, critic_only.weight)
    assert not torch.equal(states[1].actor.head.weight, states[0].actor.head.weight)  # the actor did step


def test_sac_s_critic_loss_trains_the_encoder_and_its_actor_loss_leaves_it_alone():
    config = sac_config()
    state = sac.init_state(config, CAMERA_AND_STATE, ACT, seed=1)
    conv = state.actor.encoder.convs["pixels"][0]
    assert not set(map(id, state.actor.encoder.parameters())) & {
        id(p) for group in state.actor_opt.param_groups for p in group["params"]}
    before, head = conv.weight.detach().clone(), state.actor.head.weight.detach().clone()
    # The encoder's gradient as the critic's step takes it: the actor's and the temperature's losses,
    # computed after, must add nothing to it.
    critic_step, at_critic_step = state.critic_opt.step, []
    state.critic_opt.step = lambda: at_critic_step.append(conv.weight.grad.clone()) or critic_step()
    sac.update(state, sac.prepare(state, frames_batch(CAMERA_AND_STATE), config), config)
    assert at_critic_step[0].abs().sum() > 0 and not torch.equal(conv.weight, before)
    torch.testing.assert_close(conv.weight.grad, at_critic_step[0], rtol=0, atol=0)
    assert not torch.equal(state.actor.head.weight, head)  # the actor did step


def sample_batch(frames: dict, k: int = K, n: int = 4) -> SampleBatch:
    """A frames-form reply of a replay shard, every stack of frame 0."""
    return SampleBatch(0, n, False, None, np.zeros((n, ACT), np.float32), np.zeros(n, np.float32), None,
                       np.zeros(n, bool), np.zeros(n, bool), np.arange(n), np.zeros(n, np.int64), np.ones(n) / n,
                       np.zeros(n, np.int64), frames=frames, obs_frames=np.zeros((n, k), np.int64),
                       next_obs_frames=np.zeros((n, k), np.int64))


def test_the_learner_refuses_batches_of_another_observation_or_stack():
    learner = LearnerConfig(obs_dim=0, observation=PIXELS, act_dim=ACT)
    frames = {"pixels": np.zeros((1, 3, 24, 24), np.uint8)}
    _check_observations(sample_batch(frames), learner, K)
    for batch, reason in ((sample_batch(frames, k=2), "wrong_stack"),
                          (sample_batch({"pixels": np.zeros((1, 3, 32, 32), np.uint8)}), "wrong_shape"),
                          (sample_batch({**frames, "state": np.zeros((1, 4), np.float32)}), "unknown_field")):
        with pytest.raises(ProtocolError) as error:
            _check_observations(batch, learner, K)
        assert error.value.reason == reason


def test_resuming_with_another_observation_or_stack_stops_with_one_line_naming_both(tmp_path):
    config = pixel_config()
    learner = LearnerConfig(run_dir=tmp_path, resume=True, obs_dim=0, observation=PIXELS, act_dim=ACT)
    save_checkpoint(learner.checkpoint, init_state(config, PIXELS, ACT), config, 0, ACT)
    assert _initial_state(learner, config, torch.device("cpu")).actor.observation == PIXELS
    with pytest.raises(CheckpointError, match=r"trained on observations \{pixels: uint8\[3, 24, 24\]\} stacked 3, "
                                              r"this learner's are \{pixels: .*state: float32\[4\]\} stacked 3"):
        _initial_state(replace(learner, observation=CAMERA_AND_STATE), config, torch.device("cpu"))
    with pytest.raises(CheckpointError, match="stacked 3, this learner's are .* stacked 2"):
        _initial_state(learner, replace(config, frame_stack=2), torch.device("cpu"))


@pytest.mark.parametrize("algorithm", ["td3", "sac"])
def test_updates_on_image_batches_move_every_network(algorithm):
    if algorithm == "td3":
        config, networks = pixel_config(update_repeat=2), ("actor", "critic", "target_actor", "target_critic")
        state = init_state(config, CAMERA_AND_STATE, ACT, seed=2)
        steps = GradientSteps(update, config, repeat=2, policy_delay=config.policy_delay)
    else:
        config, networks = sac_config(update_repeat=2), ("actor", "critic", "target_critic")
        state = sac.init_state(config, CAMERA_AND_STATE, ACT, seed=2)
        steps = GradientSteps(sac.update, config, repeat=2)
    before = {name: copy.deepcopy(getattr(state, name).state_dict()) for name in networks}
    for seed in range(2):
        metrics = steps(state, frames_batch(CAMERA_AND_STATE, seed=seed))
    assert state.updates == 4 and metrics["priorities"].shape == (8,)
    assert all(torch.isfinite(value).all() for value in metrics.values())
    for name in networks:
        after = getattr(state, name).state_dict()
        assert any(not torch.equal(before[name][k], after[k]) for k in after), name


def test_the_vector_keeps_its_networks_and_spec():
    state = init_state(TD3Config(hidden=(8,)), 5, ACT, seed=0)
    assert state.actor.spec == {"obs_dim": 5, "act_dim": ACT, "hidden": [8], "activation": "elu", "layer_norm": True,
                                "relative_x": False, "normalize_obs": False, "kind": "deterministic"}
    assert sorted(state.actor.state_dict()) == ["exploration_std", "head.bias", "head.weight", "trunk.0.bias",
                                                "trunk.0.weight", "trunk.1.bias", "trunk.1.weight"]
    assert not any("projection" in key for key in state.critic.state_dict())
    assert check_spec({**default_spec(41, 18), **ObservationSpec.vector(41).policy_entries()}) == default_spec(41, 18)


def test_an_image_policy_spec_says_what_an_actor_stacks():
    spec = init_state(pixel_config(), CAMERA_AND_STATE, ACT).actor.spec
    assert ObservationSpec.from_policy_spec(spec) == CAMERA_AND_STATE and spec["frame_stack"] == K
    assert spec["encoder"] == {"channels": 8, "features": 6} and "obs_dim" not in spec
    assert check_spec(spec) == spec
    with pytest.raises(ValueError, match="at least 15 x 15"):
        check_spec({**spec, "observation": ObservationSpec({"pixels": FieldSpec(np.uint8, (3, 8, 8))}).to_wire()})
    with pytest.raises(ValueError, match="float32 vector alone"):
        check_spec({**spec, "normalize_obs": True})


def test_act_takes_stacked_fields_and_the_vector_as_before():
    policy = build_policy(init_state(pixel_config(), CAMERA_AND_STATE, ACT, seed=3).actor.spec)
    rng = np.random.default_rng(0)
    obs = {"pixels": rng.integers(0, 256, (4, 9, 24, 24), dtype=np.uint8),
           "state": rng.normal(size=(4, 12)).astype(np.float32)}
    excitation = act(policy, obs, deterministic=True)
    assert excitation.shape == (4, ACT) and excitation.dtype == np.float32
    assert ((excitation >= 0) & (excitation <= 1)).all()
    assert not np.allclose(excitation, act(policy, {**obs, "pixels": 255 - obs["pixels"]}, deterministic=True))
    explored, log_prob = act_with_log_prob(policy, obs)
    assert explored.shape == (4, ACT) and log_prob.shape == (4,)
    with pytest.raises(ValueError, match="as a map of arrays; got ndarray"):
        act(policy, obs["state"])
    with pytest.raises(ValueError, match=r"as a map of arrays; got \['pixels'\]"):
        act(policy, {"pixels": obs["pixels"]})
    with pytest.raises(ValueError, match=r"shape \[4, 3, 24, 24\], this policy takes \[n, 9, 24, 24\]"):
        act(policy, {**obs, "pixels": obs["pixels"][:, :3]})
    vector = build_policy(default_spec(5, ACT))
    one = rng.normal(size=(3, 5)).astype(np.float32)
    np.testing.assert_array_equal(act(vector, one, True), act(vector, {"state": one}, True))


@pytest.mark.parametrize("algorithm", ["td3", "sac"])
def test_an_image_training_state_survives_a_checkpoint(tmp_path, algorithm):
    if algorithm == "td3":
        config, kind = pixel_config(), DeterministicPolicy
        state = init_state(config, PIXELS, ACT, seed=4)
        GradientSteps(update, config, policy_delay=1)(state, frames_batch())
    else:
        config, kind = sac_config(), Policy
        state = sac.init_state(config, PIXELS, ACT, seed=4)
        GradientSteps(sac.update, config)(state, frames_batch())
    path = save_checkpoint(checkpoint_path(tmp_path), state, config, 0, ACT)
    saved = load_checkpoint(path)
    assert saved.policy_spec == state.actor.spec and saved.config == config
    restored = saved.restore()
    for name in ("actor", "critic", "target_critic", *(["target_actor"] if algorithm == "td3" else [])):
        mine, theirs = getattr(state, name).state_dict(), getattr(restored, name).state_dict()
        assert mine.keys() == theirs.keys() and all(torch.equal(mine[k], theirs[k]) for k in mine), name
    if algorithm == "td3":
        assert restored.target_actor.encoder is restored.actor.encoder
    policy = saved.policy()
    assert isinstance(policy, kind) and policy.frame_stack == K
    obs = {"pixels": np.zeros((1, 9, 24, 24), np.uint8)}
    np.testing.assert_array_equal(act(policy, obs, True), act(state.actor, obs, True))


def test_the_command_line_takes_the_observation_and_defaults_to_drq_v2_s_stack_and_shift():
    settings = parse_settings(["--algo", "td3", "--observation", "pixels: uint8[3, 24, 24]"])
    assert settings.td3().frame_stack == 3 and settings.td3().augment_pad == 4
    assert settings.learner().observation == PIXELS
    vector = parse_settings(["--algo", "td3", "--obs-dim", "7"])
    assert vector.learner().observation is None and vector.learner().obs_dim == 7 and vector.td3().frame_stack == 1
    captured = parse_settings(["--algo", "td3", "--compile", "graphs", "--observation", str(PIXELS)])
    assert captured.learner().compile == "graphs"  # image updates are captured as CUDA graphs
    drq = parse_settings(["--algo", "sac", "--observation", str(PIXELS)]).sac()
    assert (drq.frame_stack, drq.augment_pad, drq.encoder) == (3, 4, "drq")
    for argv, message in ((["--algo", "ppo", "--observation", str(PIXELS)], "train with --algo td3 .* or sac"),
                          (["--algo", "td3", "--compile", "inductor-graphs", "--observation", str(PIXELS)],
                           "apart from eager"),
                          (["--algo", "td3", "--augment-pad", "3"], "for image observations"),
                          (["--algo", "td3", "--env-id", "Hopper-v5", "--observation", str(PIXELS)], "give one")):
        with pytest.raises(UsageError, match=message):
            parse_settings(argv)
