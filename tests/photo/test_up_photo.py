"""`l2r up` on the photo tasks, end to end: real replay, learner, actor and evaluator processes over
loopback Zenoh, the actor editing real photos with the pipeline, the learner training TD3 on the
tuner's current and goal images and the state with the photo recipe, or PPO on the enhancer's
statistics from the queue table, and best.pt kept by PSNR."""

import json
import re
import uuid

import pytest
import torch

from l2r.learner.checkpoint import load_checkpoint
from l2r.photo import ENHANCE_STATS_ID, TUNE_ID
from tests.system.test_up import finish, l2r_up, rows

pytestmark = pytest.mark.slow


def test_the_photo_tuner_trains_evaluates_and_keeps_its_best_policy_by_psnr(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = l2r_up(tmp_path / "up.out", "--env-id", TUNE_ID, "--algo", "td3", "--env-steps", "500",
                  "--seconds", "300", "--name", name, "--runs-dir", str(tmp_path), "--hidden", "32,32",
                  "--batch-size", "16", "--samples-per-insert", "4", "--random-steps", "50", "--min-replay", "50",
                  "--capacity", "1000", "--publish-every", "5", "--eval-episodes", "2", "--eval-interval", "3",
                  "--status-interval", "2", "--learner-arg=--checkpoint-interval=3")
    out = finish(proc, tmp_path / "up.out", 300)
    assert proc.returncode == 0, out
    run_dir = next(tmp_path.glob(f"{name}-*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] >= 500 and summary["updates"] > 0, summary
    assert summary["score"] == "psnr", summary
    assert re.search(r"\| eval psnr \d+\.\d\d dB \|", out), out  # the status line speaks of PSNR
    assert "frames/s" not in out  # a photo is no camera frame

    logs = run_dir / "logs"
    assert "observation {goal: uint8[3, 64, 64], pixels: uint8[3, 64, 64], state: float32[16]}" in \
        (logs / "replay.log").read_text()
    trained = [float(r["psnr"]) for r in rows(run_dir / "metrics" / "episodes.csv")]
    assert trained and all(0.0 < p <= 100.0 for p in trained), trained  # the actors' episodes too
    evaluations = rows(run_dir / "metrics" / "evaluation.csv")
    assert evaluations, "no evaluation round"  # of the untrained policy at least: a loaded machine may end first
    psnrs = [float(r["psnr"]) for r in evaluations]
    assert all(0.0 < p <= 100.0 for p in psnrs), psnrs  # PSNRs in dB (of images in [0, 1]), never NaN
    best = torch.load(run_dir / "learner" / "best.pt", weights_only=False)
    assert best["evaluation"]["score"] == "psnr"
    chosen = [float(r["psnr"]) for r in evaluations if int(r["version"]) == best["evaluation"]["version"]]
    assert best["evaluation"]["mean_psnr"] == pytest.approx(sum(chosen) / len(chosen))


def test_the_enhancer_trains_with_ppo_from_the_queue_table_and_keeps_its_best_policy_by_psnr(tmp_path):
    name = f"test-{uuid.uuid4().hex[:6]}"
    proc = l2r_up(tmp_path / "up.out", "--env-id", ENHANCE_STATS_ID, "--algo", "ppo", "--env-steps", "200",
                  "--seconds", "300", "--name", name, "--runs-dir", str(tmp_path), "--batch-size", "64",
                  "--minibatches", "2", "--epochs", "1", "--eval-episodes", "1", "--eval-interval", "2",
                  "--status-interval", "2")
    out = finish(proc, tmp_path / "up.out", 300)
    assert proc.returncode == 0, out
    run_dir = next(tmp_path.glob(f"{name}-*"))
    summary = json.loads((run_dir / "summary.json").read_text())
    assert summary["env_steps"] >= 200 and summary["updates"] > 0 and summary["score"] == "psnr", summary
    assert json.loads((run_dir / "launch.json").read_text())["recipe"]["name"] == "photo/ppo"
    trained = [float(r["psnr"]) for r in rows(run_dir / "metrics" / "episodes.csv")]
    assert trained and all(0.0 < p <= 100.0 for p in trained), trained
    best = load_checkpoint(run_dir / "learner" / "best.pt")
    assert best.evaluation["score"] == "psnr" and best.policy().spec["obs_dim"] == 35, best.evaluation
