"""A2C and REINFORCE (PPO's update at their settings) against a step worked out by hand: returns,
the policy-gradient and value losses, one RMSprop or Adam step; their selection through the
learner's command line; a checkpoint round trip under their names."""

import copy

import numpy as np
import pytest
import torch

from l2r.config import EXIT_CANNOT_START
from l2r.learner.__main__ import cli, parse_settings
from l2r.learner.a2c import A2CConfig
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.daemon import STEPS
from l2r.learner.ppo import PPOConfig, batch_from_sample, gae, init_state
from l2r.learner.reinforce import ReinforceConfig
from l2r.protocol import SampleBatch
from tests.learner.test_ppo import sample_batch

GAMMA = 0.5


def test_lambda_one_gives_monte_carlo_returns_bootstrapped_only_where_a_piece_is_cut():
    # Rows 0-1: an episode cut by its time limit after row 1 (V of its final observation is 10);
    # rows 2-3: an episode that terminates at row 3 (its next value, 8, must not count).
    # Returns from the end, gamma .5: G3 = 4; G2 = 3 + .5*4 = 5; G1 = 2 + .5*10 = 7; G0 = 1 + .5*7 = 4.5
    values = np.array([0.5, 1.0, 1.5, 2.0])
    advantages = gae(np.array([1.0, 2.0, 3.0, 4.0]), values, np.array([1.0, 10.0, 2.0, 8.0]),
                     np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.0, 1.0, 0.0, 1.0]), gamma=GAMMA, lam=1.0)
    np.testing.assert_allclose(advantages + values, [4.5, 7.0, 5.0, 4.0])


def tiny_batch(config: PPOConfig, state) -> SampleBatch:
    """Four steps: rows 0-1 an episode that terminates at row 1, rows 2-3 a piece the batch cuts
    after row 3; the actions' log-probabilities are the learner's own (an actor with its newest weights)."""
    sample = sample_batch(4, seed=3, obs_dim=3, act_dim=2, rewards=np.array([1.0, -2.0, 0.5, 3.0]))
    sample.terminated[:] = [False, True, False, False]
    sample.segment_ends[:] = [False, False, False, True]
    sample.next_obs[[0, 2]] = sample.obs[[1, 3]]  # where the trajectory goes on
    with torch.no_grad():
        batch = batch_from_sample(sample)
        sample.log_probs[:] = state.actor.evaluate(batch.obs, batch.action)[0].numpy()
    return sample


def expected_step(state, sample: SampleBatch, config: PPOConfig) -> tuple[list[torch.Tensor], float]:
    """The parameters after one step, and the value loss, computed here from the formulas."""
    state = copy.deepcopy(state)
    batch = batch_from_sample(sample)
    v = state.value(batch.obs)
    with torch.no_grad():
        v_next = state.value(batch.next_obs)
    r, gamma = batch.reward, config.gamma
    # Returns by hand (lambda 1): row 1 terminates, row 3 is cut and bootstraps.
    g3 = r[3] + gamma * v_next[3]
    g1 = r[1]
    returns = torch.stack([r[0] + gamma * g1, g1, r[2] + gamma * g3, g3]).detach()
    advantages = returns - v.detach()
    if config.normalize_advantages:
        advantages = (advantages - advantages.mean()) / (advantages.std(correction=0) + 1e-8)
    log_prob = state.actor.evaluate(batch.obs, batch.action)[0]
    policy_loss = -(advantages * log_prob).mean()  # the policy gradient's loss
    value_loss = 0.5 * (v - returns).pow(2).mean()
    (policy_loss + config.value_coef * value_loss).backward()
    value_loss = value_loss.detach()
    params = state.parameters()
    grads = [p.grad for p in params]
    norm = torch.sqrt(sum(g.pow(2).sum() for g in grads))
    scale = min(1.0, config.max_grad_norm / (float(norm) + 1e-6))
    after = []
    for p, g in zip(params, grads):
        g = g * scale
        if config.optimizer == "rmsprop":  # first step: the average of squares is (1 - 0.99) g^2
            step = g / (torch.sqrt(0.01 * g * g) + 1e-5)
        else:  # Adam's first step: bias-corrected moments g and g^2
            step = g / (g.abs() + 1e-5)
        after.append(p.detach() - config.lr * step)
    return after, value_loss.item()


@pytest.mark.parametrize("config", [A2CConfig(batch_size=4, hidden=(4,), gamma=GAMMA),
                                    ReinforceConfig(batch_size=4, hidden=(4,), gamma=GAMMA)],
                         ids=["a2c", "reinforce"])
def test_one_update_is_one_step_on_the_policy_gradient_and_value_loss_worked_by_hand(config):
    state = init_state(config, 3, 2, seed=0)
    sample = tiny_batch(config, state)
    expected, value_loss = expected_step(state, sample, config)
    # The daemon's step for the algorithm, as it trains on a queue batch.
    to_device, step, _, publish_each_batch = STEPS["a2c" if isinstance(config, A2CConfig) else "reinforce"]
    metrics = step(state, to_device(sample, None, torch.device("cpu")), sample, config, None, None)
    assert state.updates == 1 and publish_each_batch
    assert float(metrics["value_loss"]) == pytest.approx(value_loss, rel=1e-5)
    for want, got in zip(expected, state.parameters()):
        torch.testing.assert_close(got.detach(), want, rtol=1e-4, atol=1e-6)


def test_the_learner_s_algo_picks_each_algorithm_s_published_defaults_and_flags_replace_them():
    assert parse_settings(["--algo", "a2c"]).algorithm() == A2CConfig()
    assert parse_settings(["--algo", "reinforce"]).algorithm() == ReinforceConfig()
    assert parse_settings(["--algo", "ppo"]).algorithm() == PPOConfig()
    a2c = A2CConfig()
    # Stable-Baselines3's A2C: n_steps 5 of one env, RMSprop at 7e-4, lambda 1, vf_coef 0.5 on the squared error
    assert (a2c.batch_size, a2c.epochs, a2c.minibatches, a2c.lr, a2c.optimizer, a2c.gae_lambda, a2c.value_coef,
            a2c.normalize_advantages, a2c.max_grad_norm, a2c.hidden) == (5, 1, 1, 7e-4, "rmsprop", 1.0, 1.0, False,
                                                                        0.5, (64, 64))
    reinforce = ReinforceConfig()
    assert (reinforce.batch_size, reinforce.epochs, reinforce.minibatches, reinforce.lr, reinforce.optimizer,
            reinforce.gae_lambda, reinforce.normalize_advantages) == (4000, 1, 1, 3e-4, "adam", 1.0, True)
    given = parse_settings(["--algo", "a2c", "--lr", "1e-3", "--optimizer", "adam", "--normalize-advantages",
                            "--epochs", "2"]).algorithm()
    assert given == A2CConfig(lr=1e-3, optimizer="adam", normalize_advantages=True, epochs=2)
    unstandardised = parse_settings(["--algo", "reinforce", "--no-normalize-advantages"]).algorithm()
    assert unstandardised == ReinforceConfig(normalize_advantages=False)


def test_an_a2c_checkpoint_restores_its_rmsprop_state_and_a_ppo_or_adam_learner_refuses_it(tmp_path, capsys):
    config = A2CConfig(batch_size=64, hidden=(16,))
    state = init_state(config, 5, 3, seed=0)
    STEPS["a2c"][1](state, batch_from_sample(sample_batch(64)), None, config, None, None)
    save_checkpoint(checkpoint_path(tmp_path), state, config, 5, 3)
    saved = load_checkpoint(tmp_path)
    restored = saved.restore()
    assert (saved.algo, saved.config, restored.updates) == ("a2c", config, 1)
    assert isinstance(restored.optimizer, torch.optim.RMSprop)
    assert all(torch.equal(a, b) for a, b in zip(state.parameters(), restored.parameters()))
    squares = [[s["square_avg"] for s in trained.optimizer.state.values()] for trained in (state, restored)]
    assert len(squares[1]) == len(state.parameters()) and all(torch.equal(a, b) for a, b in zip(*squares))
    assert cli(["--run", "x", "--run-dir", str(tmp_path), "--resume", "--device", "cpu", "--algo", "ppo",
                "--obs-dim", "5", "--act-dim", "3", "--connect", "tcp/127.0.0.1:9"]) == EXIT_CANNOT_START
    assert "holds A2C, not a PPO training state: use --algo a2c" in capsys.readouterr().err
    assert cli(["--run", "x", "--run-dir", str(tmp_path), "--resume", "--device", "cpu", "--algo", "a2c",
                "--optimizer", "adam", "--obs-dim", "5", "--act-dim", "3", "--hidden", "16",
                "--connect", "tcp/127.0.0.1:9"]) == EXIT_CANNOT_START
    assert "holds the state of rmsprop, the settings ask for adam: use the same --optimizer" in capsys.readouterr().err
