"""`l2r up` judges evaluations by the score of the task's family (l2r.families), and speaks of them
in its terms: the runner's distance, a photo task's PSNR, a standard task's return. A real BestPolicy and RunMetrics
hear weights and evaluation rounds over loopback Zenoh as in a job; `after_run` and
`final_report` then write and say what the job left."""

import json
import logging
import re

import pytest
import zenoh

from l2r.best_policy import BestPolicy
from l2r.families import score_of
from l2r.learner.checkpoint import best_policy_path, load_checkpoint, save_policy_checkpoint
from l2r.live_status import status_line
from l2r.photo import TUNE_ID
from l2r.policy import build_policy, policy_state
from l2r.protocol import EpisodeSummary, Keys, LearnerVersion, Weights, encode, session_config
from l2r.run_metrics import RunMetrics
from l2r.supervise import ProcessGroup
from l2r.up import after_run, final_report, parse_args
from tests.conftest import free_port, wait_for

SPEC = {"obs_dim": 11, "act_dim": 3, "hidden": [8], "activation": "relu", "layer_norm": False}
# Policy versions, each evaluated on seeds 0 and 1: (return, distance, PSNR) of each episode. By
# mean return v2 beats v1, by mean distance and PSNR it does not; by mean PSNR v3 beats v1, by
# mean distance it does not. The best single episode is v2's on seed 1 by return, v1's on seed 0
# by distance, v3's on seed 0 by PSNR. The last round beats every other by each mean (so once
# best.pt holds it, every round before has been judged), but by none in a single episode.
ROUNDS = {1: [(10.0, 3.0, 20.0), (12.0, 2.0, 22.0)], 2: [(60.0, 1.0, 15.0), (80.0, 0.5, 16.0)],
          3: [(30.0, 2.0, 25.0), (20.0, 1.5, 24.0)], 4: [(75.0, 2.6, 24.8), (75.0, 2.6, 24.8)]}
EVALUATOR = 0


def job(run_dir, env_id: str, caplog) -> tuple[dict, BestPolicy, str, list[int]]:
    """What a job on `env_id` leaves after hearing ROUNDS: its summary, its BestPolicy, its last
    status line, and the versions it saved as best.pt in turn."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    keys = Keys("scores-test")
    score = score_of(env_id)
    with zenoh.open(session_config(listen=[endpoint])) as listener, \
            zenoh.open(session_config(connect=[endpoint])) as sender:
        metrics = RunMetrics(listener, keys, run_dir / "metrics", env_id=env_id, simulators={EVALUATOR: env_id})
        best = BestPolicy(listener, keys, run_dir, episodes_per_round=2, action_repeat=1, score=score)
        try:
            publishers = [sender.declare_publisher(key) for key in
                          (keys.weights, keys.learner_version, keys.episodes(EVALUATOR))]
            # A put before the sender has learnt of the listener's subscribers is dropped.
            assert wait_for(lambda: all(p.matching_status.matching for p in publishers), 10)
            weights, beacon, episodes = publishers
            params = policy_state(build_policy(SPEC))
            for version in ROUNDS:
                weights.put(encode(Weights(version, params, SPEC)))
                beacon.put(encode(LearnerVersion(version, updates=100 * version)))
            # In a job the weights come long before their round ends; here, before the round starts.
            assert wait_for(lambda: len(best._weights) == len(ROUNDS), 10)
            with caplog.at_level(logging.INFO, logger="l2r.up"):
                for version, results in ROUNDS.items():
                    for seed, (ret, distance, psnr) in enumerate(results):
                        episodes.put(encode(EpisodeSummary(
                            actor_id=EVALUATOR, env_id=seed, episode_return=ret, distance=distance, length=100,
                            policy_version=version, difficulty=0, seed=seed, evaluation=True,
                            psnr_db=psnr if env_id == TUNE_ID else None)))
                assert wait_for(lambda: metrics.episodes == 8 and best.best and best.best["version"] == 4, 10)
            saved = [int(v) for v in re.findall(r"best evaluated policy so far: v(\d+)", caplog.text)]
            line = status_line(metrics.record_status(), score)
            group = ProcessGroup([], run_dir / "logs", progress=metrics.rises, on_exit=lambda child, code: None)
            summary = after_run(run_dir, metrics, best, group, "time budget of 60 s spent", 0)
        finally:
            best.close()
            metrics.close()
    return summary, best, line, saved


def report(run_dir, env_id: str, summary: dict, *argv: str) -> str:
    args, _ = parse_args(["--env-id", env_id, "--runs-dir", str(run_dir.parent), *argv])
    return "\n".join(final_report(run_dir, summary, args, updates_before=0))


def test_a_standard_task_keeps_the_policy_and_the_episode_of_the_best_return_and_speaks_of_returns(tmp_path, caplog):
    summary, best, line, saved = job(tmp_path, "Hopper-v5", caplog)

    assert saved == [1, 2, 4]  # by distance, always 0 on Hopper, it would be v1 alone
    kept = load_checkpoint(best_policy_path(tmp_path))
    assert (kept.version, kept.updates, kept.action_repeat) == (4, 400, 1)
    assert kept.evaluation == {"version": 4, "score": "return", "mean_return": 75.0, "episodes": 2, "seeds": [0, 1],
                               "evaluator": EVALUATOR}
    assert summary["best_policy"] == {"path": str(best.path), **kept.evaluation}
    assert (summary["best_eval_episode"]["version"], summary["best_eval_episode"]["seed"]) == (2, 1)
    assert (summary["score"], summary["best_eval_score"], summary["best_eval_return"]) == ("return", 80.0, 80.0)
    assert "best_eval_distance" not in summary and "opensim_eval_return" not in summary
    assert json.loads((tmp_path / "summary.json").read_text()) == summary

    assert "| eval return 45.25 |" in line and "distance" not in line and " m " not in line
    said = report(tmp_path, "Hopper-v5", summary)
    assert "best evaluation episode return 80.00" in said
    assert f"(v4, mean return 75.00): l2r eval {best.path} --env-id Hopper-v5" in said
    assert "distance" not in said and "a longer run" not in said  # the runner's advice is the runner's


def test_the_runner_keeps_the_policy_and_the_episode_of_the_longest_distance_and_speaks_of_distances(tmp_path, caplog):
    summary, best, line, saved = job(tmp_path, "l2r/Run-v0", caplog)

    assert saved == [1, 4]
    kept = load_checkpoint(best_policy_path(tmp_path))
    # mean_distance as before scores were named, so older readers find it.
    assert kept.evaluation == {"version": 4, "score": "distance", "mean_distance": 2.6, "episodes": 2,
                               "seeds": [0, 1], "evaluator": EVALUATOR}
    assert (summary["best_eval_episode"]["version"], summary["best_eval_episode"]["seed"]) == (1, 0)
    assert (summary["score"], summary["best_eval_score"], summary["best_eval_distance"]) == ("distance", 3.0, 3.0)
    assert summary["eval_distance"] == pytest.approx(1.9) and summary["opensim_eval_distance"] is None

    assert "| eval distance 1.90 m |" in line
    said = report(tmp_path, "l2r/Run-v0", summary)
    assert "best evaluation episode distance 3.00 m" in said
    assert f"(v4, mean distance 2.60 m): l2r eval {best.path}\n" in said
    assert "a longer run: l2r up" in said


def test_a_photo_task_keeps_the_policy_and_the_episode_of_the_best_psnr_and_speaks_of_decibels(tmp_path, caplog):
    summary, best, line, saved = job(tmp_path, TUNE_ID, caplog)

    assert saved == [1, 3, 4]
    kept = load_checkpoint(best_policy_path(tmp_path))
    assert kept.evaluation == {"version": 4, "score": "psnr", "mean_psnr": 24.8, "episodes": 2, "seeds": [0, 1],
                               "evaluator": EVALUATOR}
    assert (summary["best_eval_episode"]["version"], summary["best_eval_episode"]["seed"]) == (3, 0)
    assert summary["best_eval_episode"]["psnr"] == 25.0
    assert (summary["score"], summary["best_eval_score"], summary["best_eval_psnr"]) == ("psnr", 25.0, 25.0)
    csv_header = (tmp_path / "metrics" / "evaluation.csv").read_text().splitlines()[0]
    assert csv_header.endswith(",psnr")

    assert "| eval psnr 21.45 dB |" in line
    said = report(tmp_path, TUNE_ID, summary, "--algo", "td3")
    assert "best evaluation episode psnr 25.00 dB" in said
    assert f"(v4, mean psnr 24.80 dB): l2r eval {best.path} --env-id {TUNE_ID}" in said


def earlier_best(run_dir, evaluation: dict) -> None:
    """A best.pt left by an earlier session of the run."""
    params = policy_state(build_policy(SPEC))
    save_policy_checkpoint(best_policy_path(run_dir), params, SPEC, 9, 900, 1, evaluation)


def test_a_resumed_runner_job_must_beat_a_best_pt_from_before_scores_were_named(tmp_path, caplog):
    earlier_best(tmp_path, {"version": 9, "mean_distance": 2.55, "episodes": 2, "seeds": [0, 1]})
    _, _, _, saved = job(tmp_path, "l2r/Run-v0", caplog)
    assert saved == [4]  # v1's 2.5 m does not beat it


def test_a_resumed_standard_job_replaces_a_best_pt_chosen_by_another_score(tmp_path, caplog):
    # What a Hopper job kept before best.pt followed the return: one chosen by distance, 0 on Hopper.
    earlier_best(tmp_path, {"version": 9, "mean_distance": 0.0, "episodes": 2, "seeds": [0, 1]})
    _, _, _, saved = job(tmp_path, "Hopper-v5", caplog)
    assert saved == [1, 2, 4]
