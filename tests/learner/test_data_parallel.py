"""Two learner processes on loopback (gloo): different seeds and batches, identical weights.

On CPU here and in CI; on one GPU shared by both ranks where CUDA is present. SAC, and TD3 (whose
actor steps on every second update)."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from tests.conftest import free_port

REPO = Path(__file__).resolve().parents[2]
STEPS = 5


def worker(rank: int, world_size: int, url: str, out: str, device: str = "cpu", algo: str = "sac") -> None:
    """One rank: start from rank 0's weights, train on its own batches, record weights per step."""
    from l2r.learner.checkpoint import ALGORITHMS
    from l2r.learner.distributed import close_distributed, init_distributed
    from l2r.learner.sac import batch_from_numpy
    from l2r.learner.steps import GradientSteps

    torch.set_num_threads(1)
    init_distributed(world_size, rank, url, torch.device(device), timeout_s=60)
    config_class, algorithm = ALGORITHMS[algo]
    config = config_class(hidden=(16, 16), precision="float32")
    state = algorithm.init_state(config, 5, 3, device, seed=100 + rank)  # different on purpose
    algorithm.broadcast_state(state)
    steps = GradientSteps(algorithm.update, config, policy_delay=getattr(config, "policy_delay", None))  # as the daemon
    targets = [state.target_critic, *([state.target_actor] if algo == "td3" else [])]
    rng = np.random.default_rng(rank)  # each rank samples its own batches
    records = []
    for _ in range(STEPS + 1):
        flat = torch.cat([p.detach().reshape(-1) for p in [*state.parameters(),
                                                          *(p for t in targets for p in t.parameters())]])
        records.append(flat.tolist())
        batch = batch_from_numpy(rng.normal(size=(32, 5)), rng.random((32, 3)), rng.normal(size=32),
                                 rng.normal(size=(32, 5)), rng.random(32) < 0.1, device=device)
        steps(state, batch)
    Path(out).write_text(json.dumps(records))
    close_distributed()


@pytest.mark.slow
@pytest.mark.parametrize("device, algo", [("cpu", "sac"), ("cpu", "td3"), pytest.param(
    "cuda", "sac", marks=pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device here"))])
def test_two_learners_hold_identical_weights_after_every_step(tmp_path, device, algo):
    url = f"tcp://127.0.0.1:{free_port()}"
    outs = [tmp_path / f"rank{r}.json" for r in range(2)]
    procs = [subprocess.Popen([sys.executable, "-c", f"from tests.learner.test_data_parallel import worker; "
                               f"worker({r}, 2, {url!r}, {str(outs[r])!r}, {device!r}, {algo!r})"], cwd=REPO,
                              stdout=subprocess.PIPE, stderr=subprocess.STDOUT) for r in range(2)]
    for proc in procs:
        output, _ = proc.communicate(timeout=120)
        assert proc.returncode == 0, output.decode(errors="replace")
    rank0, rank1 = (np.array(json.loads(out.read_text())) for out in outs)
    assert rank0.shape[0] == STEPS + 1
    np.testing.assert_array_equal(rank0, rank1)  # bit for bit, after every step
    assert not np.array_equal(rank0[0], rank0[-1])  # and they did train


def test_ranks_on_this_host_come_from_torchrun_and_a_bad_value_is_logged_not_fatal(monkeypatch, caplog):
    from l2r.learner.distributed import ranks_on_this_host

    monkeypatch.delenv("LOCAL_WORLD_SIZE", raising=False)
    assert ranks_on_this_host(4) == 4  # l2r up: every rank on this host
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "2")
    assert ranks_on_this_host(4) == 2
    monkeypatch.setenv("LOCAL_WORLD_SIZE", "two")
    assert ranks_on_this_host(4) == 4
    assert "LOCAL_WORLD_SIZE='two'" in caplog.text
