"""Gradient steps eager, compiled and captured: the same training, counted outside the update."""

import copy
import shutil

import numpy as np
import pytest
import torch

from l2r.learner import sac
from l2r.learner.distributed import DeviceUnavailable
from l2r.learner.steps import WARMUP_CALLS, GradientSteps, resolve_mode
from tests.learner.test_sac import ACT, OBS, random_batch, small_config

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
COMPILER = pytest.mark.skipif(not (shutil.which("c++") or shutil.which("g++")),
                              reason="inductor needs a C++ compiler on CPU")


@pytest.mark.parametrize("device, mode", [
    pytest.param("cpu", "inductor", marks=[COMPILER, pytest.mark.compile]),
    pytest.param("cuda", "graphs", marks=CUDA),
    pytest.param("cuda", "inductor", marks=[CUDA, pytest.mark.compile]),
    pytest.param("cuda", "inductor-graphs", marks=[CUDA, pytest.mark.compile]),
])
def test_compiled_steps_train_as_the_eager_ones(device, mode):
    # Large tau and learning rates, so that a skipped Polyak copy or optimizer step shows at once;
    # normalised inputs, whose statistics change outside the update (in prepare) between calls.
    config = small_config(hidden=(16,), batch_size=32, tau=0.25, actor_lr=1e-2, critic_lr=1e-2, alpha_lr=1e-2,
                          normalize_obs=True)
    eager_state = sac.init_state(config, OBS, ACT, device, seed=0)
    compiled_state = copy.deepcopy(eager_state)
    eager = GradientSteps(sac.update, config, "off", device, repeat=2)
    compiled = GradientSteps(sac.update, config, mode, device, repeat=2)
    # Past the warm-up, so that graphs are captured and then replayed.
    for call in range(WARMUP_CALLS + 3):
        rng = np.random.default_rng(call)
        batch = sac.batch_from_numpy(rng.normal(size=(32, OBS)), rng.random((32, ACT)), rng.normal(size=32),
                                     rng.normal(size=(32, OBS)), rng.random(32) < 0.2, rng.random(32), device)
        torch.manual_seed(call)
        expected = eager(eager_state, sac.prepare(eager_state, batch, config))
        expected = {name: value.clone() for name, value in expected.items()}  # a graph's outputs are overwritten
        torch.manual_seed(call)
        got = compiled(compiled_state, sac.prepare(compiled_state, batch, config))
        for name in expected:
            torch.testing.assert_close(got[name], expected[name], rtol=1e-4, atol=1e-5, msg=f"{name}, call {call}")
    assert compiled_state.updates == eager_state.updates == 2 * (WARMUP_CALLS + 3)
    for part in ("actor", "critic", "target_critic", "critic_opt", "actor_opt", "alpha_opt"):
        torch.testing.assert_close(getattr(compiled_state, part).state_dict(), getattr(eager_state, part).state_dict(),
                                   rtol=1e-4, atol=1e-5, msg=part)
    torch.testing.assert_close(compiled_state.log_alpha, eager_state.log_alpha, rtol=1e-4, atol=1e-6)


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


def test_auto_is_graphs_on_cuda_and_off_on_cpu_and_graphs_need_cuda():
    assert resolve_mode("auto", torch.device("cuda")) == "graphs"
    assert resolve_mode("auto", torch.device("cpu")) == "off"
    assert resolve_mode("inductor", torch.device("cpu")) == "inductor"
    for mode in ("graphs", "inductor-graphs"):
        with pytest.raises(DeviceUnavailable, match="needs a CUDA device"):
            resolve_mode(mode, torch.device("cpu"))
    with pytest.raises(ValueError, match="compile mode must be one of"):
        resolve_mode("fast", torch.device("cpu"))
