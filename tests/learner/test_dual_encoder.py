"""RLPixTuner's dual-path encoder (`--encoder dual`): its widths for the photo tuner's two images
beside their statistics, its spec through a weights message and a checkpoint, TD3 updates through
it, the one-line refusals; and a spec from before encoder kinds, which builds DrQ-v2's encoder."""

import copy

import numpy as np
import pytest
import torch

from l2r.config import UsageError
from l2r.encoders import DUAL, PixelEncoder
from l2r.learner.__main__ import parse_settings
from l2r.learner.checkpoint import CheckpointError, checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.daemon import LearnerConfig, _initial_state
from l2r.learner.steps import GradientSteps
from l2r.learner.td3 import TD3Config, init_state, update
from l2r.policy import act, build_policy, check_spec, load_policy_state
from l2r.protocol import ObservationSpec, Weights, decode, encode
from tests.learner.test_pixels import frames_batch

TUNER = ObservationSpec.parse("goal: uint8[3, 64, 64], pixels: uint8[3, 64, 64], state: float32[16]")
"""l2r/PhotoTune-v0's observation."""
ACT, K = 9, 3


def dual_config(**overrides) -> TD3Config:
    base = dict(hidden=(16,), batch_size=8, precision="float32", frame_stack=1, augment_pad=0, encoder=DUAL,
                encoder_channels=4, encoder_features=6, policy_delay=1)
    return TD3Config(**(base | overrides))


def tuner_obs(n: int, seed: int = 0, stack: int = 1) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(seed)
    return {"goal": rng.integers(0, 256, (n, 3 * stack, 64, 64), dtype=np.uint8),
            "pixels": rng.integers(0, 256, (n, 3 * stack, 64, 64), dtype=np.uint8),
            "state": rng.normal(size=(n, 16 * stack)).astype(np.float32)}


def test_each_image_has_a_pooled_global_path_beside_a_local_grid_and_the_statistics_follow():
    encoder = PixelEncoder(TUNER, K, channels=4, kind=DUAL)
    # Per image: 4 global values and 4 per cell of the 8 x 8 local grid; the statistics of 3 frames.
    assert list(encoder.convs) == ["goal", "pixels"] and encoder.conv_dim == 2 * 4 * (1 + 64)
    assert encoder.vector_dim == 3 * 16
    obs = {name: torch.as_tensor(array) for name, array in tuner_obs(5, stack=K).items()}
    embedding = encoder(obs)
    assert embedding.shape == (5, 520 + 48) and torch.equal(embedding[:, 520:], obs["state"])
    for i, name in enumerate(("goal", "pixels")):  # each image scaled to -0.5 ... 0.5, global part first
        view, scaled = encoder.convs[name], obs[name] / 255.0 - 0.5
        torch.testing.assert_close(embedding[:, 260 * i:260 * i + 4], view.global_path(scaled))
        torch.testing.assert_close(embedding[:, 260 * i + 4:260 * (i + 1)], view.local_path(scaled))
    # The local grid keeps where things are: an image changed in its top-left corner alone moves the
    # first cell's values, not the last's.
    corner = {**obs, "pixels": obs["pixels"].clone()}
    corner["pixels"][:, :, :4, :4] = 255 - corner["pixels"][:, :, :4, :4]
    local = (encoder(corner) - embedding)[:, 264:520].reshape(5, 4, 8, 8)
    assert local[:, :, 0, 0].abs().sum() > 0 and local[:, :, 7, 7].abs().sum() == 0
    # The global path sees the image averaged over 2 x 2 blocks, the local path every pixel: rows
    # swapped within each block change the local values alone.
    swapped = {**obs, "pixels": obs["pixels"].unflatten(2, (32, 2)).flip(3).flatten(2, 3)}
    change = encoder(swapped) - embedding
    torch.testing.assert_close(change[:, 260:264], torch.zeros(5, 4))
    assert change[:, 264:520].abs().amax() > 1e-3
    assert PixelEncoder(ObservationSpec.parse("pixels: uint8[3, 84, 84]"), 3, kind=DUAL).conv_dim == 32 * 65


def test_a_dual_policy_travels_in_a_weights_message_and_a_checkpoint_and_acts_the_same(tmp_path):
    config = dual_config()
    state = init_state(config, TUNER, ACT, seed=0)
    spec = state.actor.spec
    assert spec["encoder"] == {"kind": "dual", "channels": 4, "features": 6} and check_spec(spec) == spec
    obs = tuner_obs(4)
    expected = act(state.actor, obs, deterministic=True)
    message = decode(encode(Weights(3, {name: t.numpy() for name, t in state.actor.state_dict().items()}, spec)),
                     Weights)
    policy = build_policy(message.spec)
    load_policy_state(policy, message.params)
    np.testing.assert_array_equal(act(policy, obs, deterministic=True), expected)
    saved = load_checkpoint(save_checkpoint(checkpoint_path(tmp_path), state, config, 0, ACT))
    assert saved.policy_spec == spec and saved.config.encoder == DUAL
    np.testing.assert_array_equal(act(saved.policy(), obs, deterministic=True), expected)
    np.testing.assert_array_equal(act(saved.restore().actor, obs, deterministic=True), expected)
    # Resumed with DrQ-v2's encoder asked for, the checkpoint is refused in one line.
    learner = LearnerConfig(run_dir=tmp_path, resume=True, obs_dim=0, observation=TUNER, act_dim=ACT)
    with pytest.raises(CheckpointError, match=r"'kind': 'dual'.*the settings ask for"):
        _initial_state(learner, dual_config(encoder="drq"), torch.device("cpu"))


def test_a_spec_without_a_kind_builds_drq_v2_s_encoder_as_before():
    spec = init_state(dual_config(encoder="drq"), TUNER, ACT).actor.spec
    assert spec["encoder"] == {"channels": 4, "features": 6}  # as every spec from before kinds
    assert check_spec({**spec, "encoder": {"kind": "drq", "channels": 4, "features": 6}}) == spec
    encoder_keys = sorted(key for key in build_policy(spec).state_dict() if key.startswith("encoder."))
    assert encoder_keys == [f"encoder.convs.{field}.{layer}.{p}" for field in ("goal", "pixels")
                            for layer in (0, 2, 4, 6) for p in ("bias", "weight")]


def test_td3_updates_through_the_dual_encoder_move_every_network_and_both_paths():
    config = dual_config(update_repeat=2, frame_stack=K)  # test_pixels.frames_batch stacks K frames
    state = init_state(config, TUNER, ACT, seed=1)
    networks = ("actor", "critic", "target_actor", "target_critic")
    before = {name: copy.deepcopy(getattr(state, name).state_dict()) for name in networks}
    steps = GradientSteps(update, config, repeat=2, policy_delay=config.policy_delay)
    metrics = steps(state, frames_batch(TUNER, n=8, act_dim=ACT))
    assert state.updates == 2 and all(torch.isfinite(value).all() for value in metrics.values())
    for name in networks:
        after = getattr(state, name).state_dict()
        assert any(not torch.equal(before[name][k], after[k]) for k in after), name
    after = state.actor.state_dict()
    for path in ("global_path", "local_path"):
        key = f"encoder.convs.goal.{path}.{1 if path == 'global_path' else 0}.weight"
        assert not torch.equal(before["actor"][key], after[key]), key


def test_an_unknown_kind_and_images_too_small_for_the_dual_path_are_refused_in_one_line():
    spec = init_state(dual_config(), TUNER, ACT).actor.spec
    small = ObservationSpec.parse("pixels: uint8[3, 31, 64]").to_wire()
    for bad, message in (({**spec, "encoder": {"kind": "vit"}}, r"encoder 'kind' must be one of \['drq', 'dual'\], "
                                                                 r"got 'vit'"),
                         ({**spec, "observation": small}, r"'pixels': the dual encoder takes uint8\[C, H, W\] images "
                                                          r"of at least 32 x 32, got uint8\[3, 31, 64\]")):
        with pytest.raises(ValueError, match=message) as error:
            check_spec(bad)
        assert "\n" not in str(error.value)
    check_spec({**spec, "observation": small, "encoder": {}})  # DrQ-v2's takes it
    with pytest.raises(ValueError, match="encoder must be one of"):
        dual_config(encoder="vit")
    with pytest.raises(UsageError, match="--encoder are for image observations"):
        parse_settings(["--algo", "td3", "--obs-dim", "7", "--encoder", "dual"])
    settings = parse_settings(["--algo", "td3", "--observation", str(TUNER), "--encoder", "dual"])
    assert settings.td3().encoder == DUAL
    assert parse_settings(["--algo", "td3", "--observation", str(TUNER)]).td3().encoder == "drq"
