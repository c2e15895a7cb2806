"""Gradient steps eager, compiled and captured: the same training, counted outside the update."""

import copy
import shutil

import numpy as np
import pytest
import torch

from l2r.learner import sac, td3
from l2r.learner import steps as steps_module
from l2r.learner.distributed import DeviceUnavailable
from l2r.learner.steps import WARMUP_CALLS, GradientSteps, resolve_mode
from tests.learner.test_pixels import CAMERA_AND_STATE, K, pixel_config, sac_config
from tests.learner.test_sac import ACT, OBS, random_batch, small_config
from tests.learner.test_td3 import small_config as td3_config

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
COMPILER = pytest.mark.skipif(not (shutil.which("c++") or shutil.which("g++")),
                              reason="inductor needs a C++ compiler on CPU")


def vector_batch(call: int, device: str) -> sac.Batch:
    rng = np.random.default_rng(call)
    return sac.batch_from_numpy(rng.normal(size=(32, OBS)), rng.random((32, ACT)), rng.normal(size=32),
                                rng.normal(size=(32, OBS)), rng.random(32) < 0.2, rng.random(32), device,
                                rng.random(32))


def image_batch(call: int, device: str) -> sac.Batch:
    """Camera frames and a state vector, stacked from a batch's distinct frames, as the replay sends them."""
    rng = np.random.default_rng(call)
    frames = {"pixels": rng.integers(0, 256, (16, 3, 24, 24), dtype=np.uint8),
              "state": rng.normal(size=(16, 4)).astype(np.float32)}
    rows = rng.integers(0, 16, (2, 8, K))
    return sac.batch_from_frames(frames, rows[0], rows[1], rng.random((8, ACT)), rng.normal(size=8),
                                 rng.random(8) < 0.2, device=device, discounts=rng.random(8))


def sac_setup():
    return sac, small_config(hidden=(16,), batch_size=32, tau=0.25, actor_lr=1e-2, critic_lr=1e-2, alpha_lr=1e-2,
                             normalize_obs=True, update_repeat=2), OBS, vector_batch


def td3_setup():
    # The target noise at the scheduled exploration std, which changes outside the update between calls;
    # 3 updates a batch with an actor step every 2nd: two patterns of actor steps, alternating.
    return td3, td3_config(hidden=(16,), batch_size=32, tau=0.25, actor_lr=1e-2, critic_lr=1e-2,
                           normalize_obs=True, update_repeat=3, policy_delay=2, target_noise=None,
                           exploration_std_start=1.0, exploration_std_end=0.1,
                           exploration_std_updates=60), OBS, vector_batch


def drqv2_setup():
    # DrQ-v2 on camera frames beside a state: the random shift drawn inside each update, n-step discounts.
    return td3, pixel_config(update_repeat=2, actor_lr=1e-2, critic_lr=1e-2, tau=0.25), CAMERA_AND_STATE, image_batch


def drq_setup():
    # DrQ (SAC) on the same: the shift, the policy's draws and the temperature's step inside each update.
    return sac, sac_config(update_repeat=2, actor_lr=1e-2, critic_lr=1e-2, alpha_lr=1e-2, tau=0.25), \
        CAMERA_AND_STATE, image_batch


def case(setup, device: str, mode: str, *marks):
    return pytest.param(setup, device, mode, marks=list(marks), id=f"{device}-{mode}-{setup.__name__}")


CPU_INDUCTOR = ("cpu", "inductor", COMPILER, pytest.mark.compile)
CUDA_MODES = [("cuda", "graphs", CUDA), ("cuda", "inductor", CUDA, pytest.mark.compile),
              ("cuda", "inductor-graphs", CUDA, pytest.mark.compile)]


# Image updates are captured as eager's kernels (graphs): DrQ-v2's under inductor kept eager's losses on
# a CPU but not on an H200 (2026-11-27), and the learner refuses inductor for images.
@pytest.mark.parametrize("setup, device, mode",
                         [case(setup, *mode) for setup in (sac_setup, td3_setup)
                          for mode in (CPU_INDUCTOR, *CUDA_MODES)]
                         + [case(setup, *CUDA_MODES[0]) for setup in (drqv2_setup, drq_setup)])
def test_compiled_steps_train_as_the_eager_ones(setup, device, mode):
    # Large tau and learning rates, so that a skipped Polyak copy or optimizer step shows at once;
    # normalised inputs, whose statistics change outside the update (in prepare) between calls;
    # n-step discounts, a batch field the graphs must copy in too.
    algorithm, config, observation, batch_of = setup()
    delay = getattr(config, "policy_delay", None)
    eager_state = algorithm.init_state(config, observation, ACT, device, seed=0)
    compiled_state = copy.deepcopy(eager_state)
    eager = GradientSteps(algorithm.update, config, "off", device, config.update_repeat, delay)
    compiled = GradientSteps(algorithm.update, config, mode, device, config.update_repeat, delay)
    # Past the warm-up of every pattern of actor steps, so that each graph is captured, then replayed.
    calls = (WARMUP_CALLS + 3) * (delay or 1)
    for call in range(calls):
        batch = batch_of(call, device)
        results = []
        for state, steps in ((eager_state, eager), (compiled_state, compiled)):
            torch.manual_seed(call)
            metrics = steps(state, algorithm.prepare(state, batch, config))
            results.append({name: value.clone() for name, value in metrics.items()})  # a graph's are overwritten
            if algorithm is td3:
                td3.follow_exploration_schedule(state, config)
        expected, got = results
        assert got.keys() == expected.keys(), call
        for name in expected:
            torch.testing.assert_close(got[name], expected[name], rtol=1e-4, atol=1e-5, msg=f"{name}, call {call}")
    assert compiled_state.updates == eager_state.updates == config.update_repeat * calls
    torch.testing.assert_close(compiled_state.state_dict(), eager_state.state_dict(), rtol=1e-4, atol=1e-5)


def test_a_graph_s_static_batch_copies_every_tensor_of_an_image_batch_s_observation_maps():
    batch = image_batch(0, "cpu")
    static = steps_module._cloned(batch)
    fields, copies = steps_module._fields(batch), steps_module._fields(static)
    assert [name for name, _ in fields] == [name for name, _ in copies]
    assert {"obs.pixels", "obs.state", "next_obs.pixels", "next_obs.state", "discounts"} <= {name for name, _ in fields}
    for (name, value), (_, copy_) in zip(fields, copies):
        assert torch.equal(value, copy_) and value.data_ptr() != copy_.data_ptr(), name
    # A graph is specific to the shapes of every field: other images, another graph.
    other = image_batch(0, "cpu")
    other.obs["pixels"] = other.obs["pixels"][:, :, :20]
    assert steps_module._shape(other) != steps_module._shape(batch)


def test_steps_count_the_updates_of_their_one_state():
    config = small_config()
    state = sac.init_state(config, OBS, ACT, seed=0)
    steps = GradientSteps(sac.update, config, repeat=3)
    before = copy.deepcopy(state.critic.state_dict())
    steps(state, random_batch())
    assert state.updates == 3
    assert any(not torch.equal(before[k], v) for k, v in state.critic.state_dict().items())
    with pytest.raises(ValueError, match="state it first ran on"):
        steps(sac.init_state(config, OBS, ACT, seed=1), random_batch())


def test_auto_captures_graphs_on_cuda_compiled_where_triton_is_and_graphs_need_cuda(monkeypatch):
    monkeypatch.setattr(steps_module, "has_triton", lambda: True)
    assert resolve_mode("auto", torch.device("cuda")) == "inductor-graphs"
    assert resolve_mode("auto", torch.device("cuda"), images=True) == "graphs"
    assert resolve_mode("auto", torch.device("cpu"), images=True) == "off"
    monkeypatch.setattr(steps_module, "has_triton", lambda: False)
    assert resolve_mode("auto", torch.device("cuda")) == "graphs"
    assert resolve_mode("auto", torch.device("cpu")) == "off"
    assert resolve_mode("inductor", torch.device("cpu")) == "inductor"
    for mode in ("graphs", "inductor-graphs"):
        with pytest.raises(DeviceUnavailable, match="needs a CUDA device"):
            resolve_mode(mode, torch.device("cpu"))
    with pytest.raises(ValueError, match="compile mode must be one of"):
        resolve_mode("fast", torch.device("cpu"))
