"""The tuners of l2r.photo.tune and `l2r photo tune` / `l2r photo compare`, on real photos from the
wheels, real image files the tests write, and the real command in a subprocess."""

import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from l2r.learner import td3
from l2r.learner.checkpoint import save_policy_checkpoint
from l2r.photo import TUNE_ID, TUNE_IDS, photos, tune
from l2r.photo.env import psnr_db
from l2r.photo.pipeline import NAMES, finish, params_from_actions
from l2r.policy import policy_state
from l2r.spaces import task_spaces
from tests.conftest import ROOT

GOAL_ACTIONS = np.array([0.4, -0.3, 0.2, 0.5, -0.6, 0.3, 0.2, -0.4, 0.6], np.float32)


@pytest.fixture(scope="module")
def problem() -> tune.Problem:
    return tune.held_out_problems(1, seed=0)[0]


def input_psnr(problem: tune.Problem) -> float:
    return float(psnr_db(problem.source[None], problem.goal[None])[0])


def test_the_optimisers_gain_with_their_budget_and_cmaes_at_200_queries_beats_the_input(problem):
    assert problem.name.split("@")[0] in photos.SPLITS["test"]  # a held-out photo
    cma, random = tune.cmaes(problem, 200, seed=0), tune.random_search(problem, 200, seed=0)
    for trace in (cma, random):
        assert trace.psnr_db.shape == (200,) and trace.actions.shape == (200, 9)
        assert np.all(np.abs(trace.actions) <= 1.0)
        # Each value is the query of its actions, so the best of n queries is what a budget of n returns.
        assert trace.psnr_db[7] == pytest.approx(tune.query(problem, trace.actions[7]))
    best = {name: [t.psnr_db[t.best(n)] for n in (10, 50, 200)] for name, t in (("cma", cma), ("random", random))}
    assert best["cma"][0] < best["cma"][1] < best["cma"][2], best
    assert best["random"][0] <= best["random"][1] <= best["random"][2], best
    assert best["cma"][2] > input_psnr(problem) + 8.0 and best["cma"][2] > best["random"][2], best


def test_a_budget_cut_inside_a_generation_spends_exactly_its_queries_and_a_seed_repeats(problem):
    trace = tune.cmaes(problem, 23, seed=5)  # generations of 10
    assert len(trace.psnr_db) == 23
    np.testing.assert_array_equal(trace.psnr_db, tune.cmaes(problem, 23, seed=5).psnr_db)
    np.testing.assert_array_equal(trace.psnr_db, tune.cmaes(problem, 40, seed=5).psnr_db[:23])


def untrained_policy_checkpoint(path, env_id=TUNE_ID):
    """An untrained TD3 policy of a photo task, saved as `l2r up` saves best.pt."""
    observation, act_dim = task_spaces(env_id)
    state = td3.init_state(td3.TD3Config(hidden=(16,), precision="float32"), observation, act_dim, seed=0)
    return save_policy_checkpoint(path, policy_state(state.actor), dict(state.actor.spec), version=1, updates=0,
                                  action_repeat=1, evaluation={})


@pytest.mark.parametrize("env_id", TUNE_IDS)
def test_a_policy_tunes_in_its_episode_s_queries_through_the_task_it_was_trained_on(problem, tmp_path, env_id):
    from l2r.learner.checkpoint import load_checkpoint

    policy = load_checkpoint(untrained_policy_checkpoint(tmp_path / "best.pt", env_id)).policy()
    trace = tune.policy_tune(policy, problem)
    assert 1 <= len(trace.psnr_db) <= tune.POLICY_QUERIES
    # The task's own PSNR of each step is that of the pipeline run with the actions recorded.
    for actions, psnr in zip(trace.actions, trace.psnr_db):
        assert psnr == pytest.approx(tune.query(problem, actions), abs=1e-4)
    # Deterministic: the same policy on the same problem queries the same parameters.
    np.testing.assert_array_equal(trace.actions, tune.policy_tune(policy, problem).actions)


def l2r_photo(*argv: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "l2r.cli", "photo", *argv], cwd=ROOT, capture_output=True, text=True,
                          timeout=300)


def test_compare_json_holds_every_method_keyed_by_budget_and_the_policy_with_a_checkpoint(tmp_path):
    checkpoint = untrained_policy_checkpoint(tmp_path / "best.pt")
    run = l2r_photo("compare", "--photos", "1", "--budgets", "10,20", "--seed", "3", "--checkpoint", str(checkpoint),
                    "--json")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert len(lines) == 1
    result = json.loads(lines[0])
    assert result["photos"] == 1 and result["policy_queries"] == 10
    for key in ("input_psnr_db", "input_ssim", "policy_psnr_db", "policy_ssim"):
        assert isinstance(result[key], float), key
    for key in ("random_psnr_db", "cmaes_psnr_db", "random_ssim", "cmaes_ssim"):
        assert set(result[key]) == {"10", "20"} and all(isinstance(v, float) for v in result[key].values()), key
    assert result["cmaes_psnr_db"]["20"] >= result["cmaes_psnr_db"]["10"] > result["input_psnr_db"]
    assert 0.0 < result["input_ssim"] < 1.0


def test_compare_without_a_checkpoint_reports_no_policy_and_prints_a_table():
    run = l2r_photo("compare", "--photos", "1", "--budgets", "10")
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[1].split() == ["method", "queries", "PSNR", "(dB)", "SSIM"]
    assert [line.split()[0] for line in lines[2:]] == ["input", "random", "CMA-ES"]  # no policy row


def test_compare_on_other_scenes_looks_names_each_problem_s_look():
    run = l2r_photo("compare", "--photos", "2", "--budgets", "10", "--goals", "looks", "--json")
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["goals"] == "looks" and len(result["problems"]) == 2
    assert all(" in " in name and name.endswith("'s look") for name in result["problems"])
    random_goals = json.loads(l2r_photo("compare", "--photos", "2", "--budgets", "10", "--json").stdout)
    assert random_goals["goals"] == "random" and random_goals["input_psnr_db"] != result["input_psnr_db"]


def write_pair(tmp_path, size=(96, 128)):
    """An input (a crop of chelsea, not square) and its goal finished with GOAL_ACTIONS, as PNG files."""
    source = photos.load_photo("chelsea")[:, :size[0], :size[1]]
    goal = photos.to_uint8(finish((source / np.float32(255))[None], params_from_actions(GOAL_ACTIONS))[0])
    paths = tmp_path / "input.png", tmp_path / "goal.png"
    for path, image in zip(paths, (source, goal)):
        iio.imwrite(path, image.transpose(1, 2, 0))
    return paths


def test_tune_writes_the_finished_png_and_its_json_says_what_it_reached(tmp_path):
    source, goal = write_pair(tmp_path)
    out = tmp_path / "out.png"
    run = l2r_photo("tune", str(source), "--goal", str(goal), "--optimizer", "cmaes", "--queries", "60",
                    "--out", str(out), "--json")
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    written = iio.imread(out)
    assert written.shape == (96, 128, 3) and written.dtype == np.uint8
    as_float = written.transpose(2, 0, 1)[None] / np.float32(255)
    goal_float = iio.imread(goal).transpose(2, 0, 1)[None] / np.float32(255)
    assert result["psnr_db"] == pytest.approx(float(psnr_db(as_float, goal_float)[0]), abs=1e-3)
    assert result["psnr_db"] > result["input_psnr_db"] + 5.0, result
    assert list(result["params"]) == list(NAMES) and len(result["queries"]) == 60
    assert 0.0 < result["ssim"] <= 1.0


def test_tune_with_a_checkpoint_queries_as_the_policy_s_episode(tmp_path):
    source, goal = write_pair(tmp_path)
    checkpoint = untrained_policy_checkpoint(tmp_path / "best.pt")
    run = l2r_photo("tune", str(source), "--goal", str(goal), "--checkpoint", str(checkpoint),
                    "--out", str(tmp_path / "out.png"))
    assert run.returncode == 0, run.stderr
    lines = run.stdout.splitlines()
    assert lines[0].startswith("query    1:") and "policy" in lines[-1]
    assert 2 <= len(lines) - 2 <= tune.POLICY_QUERIES
    assert lines[-2].startswith("parameters: exposure_ev ")


def test_tune_says_in_one_line_what_is_wrong_with_its_files(tmp_path):
    source, goal = write_pair(tmp_path)
    missing = l2r_photo("tune", str(tmp_path / "nothing.png"), "--goal", str(goal), "--out", str(tmp_path / "o.png"))
    assert missing.returncode == 1 and missing.stderr.count("\n") == 1 and "nothing.png: no such file" in missing.stderr
    other = tmp_path / "small.png"
    iio.imwrite(other, np.zeros((64, 64, 3), np.uint8))
    mismatch = l2r_photo("tune", str(source), "--goal", str(other), "--out", str(tmp_path / "o.png"))
    assert mismatch.returncode == 1 and mismatch.stderr.count("\n") == 1, mismatch.stderr
    assert "128 x 96" in mismatch.stderr and "64 x 64" in mismatch.stderr
    assert not (tmp_path / "o.png").exists()


def test_l2r_eval_of_a_photo_policy_speaks_of_the_psnr_each_episode_ends_at(tmp_path):
    checkpoint = untrained_policy_checkpoint(tmp_path / "best.pt")
    run = subprocess.run([sys.executable, "-m", "l2r.cli", "eval", str(checkpoint), "--env-id", TUNE_ID,
                          "--episodes", "2", "--json"], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    result = json.loads(run.stdout)
    assert result["score"] == "psnr" and len(result["psnrs_db"]) == 2
    assert result["mean_psnr"] == pytest.approx(sum(result["psnrs_db"]) / 2) and 3.0 < result["mean_psnr"] < 100.0


def test_compare_crops_the_held_out_inputs_of_a_fivek_folder(tmp_path):
    photo = photos.load_photo("astronaut").transpose(1, 2, 0)
    for folder in ("input", "expertC_gt"):
        (tmp_path / folder).mkdir()
        for k in range(10):  # the last tenth in name order, a9, is held out
            iio.imwrite(tmp_path / folder / f"a{k}.png", np.roll(photo, 40 * k, axis=1)[:300, :300])
    problems = tune.held_out_problems(2, seed=0, folder=tmp_path)
    assert [p.name for p in problems] == ["a9@0", "a9@1"]
    run = l2r_photo("compare", str(tmp_path), "--photos", "1", "--budgets", "10", "--json")
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout)["problems"] == ["a9@0"]
    missing = l2r_photo("compare", str(tmp_path / "nowhere"), "--photos", "1", "--budgets", "10")
    assert missing.returncode == 1 and missing.stderr.count("\n") == 1 and "is not a folder" in missing.stderr
