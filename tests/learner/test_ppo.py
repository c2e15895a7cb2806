"""PPO's parts against numbers worked out by hand, and its update on small networks."""

import numpy as np
import pytest
import torch

from l2r.config import EXIT_CANNOT_START
from l2r.learner.__main__ import cli
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.ppo import (
    LAG_CORRECTIONS, Batch, PPOConfig, batch_from_sample, clipped_surrogate, gae, init_state, update, vtrace,
)
from l2r.policy import act_with_log_prob, to_tanh_space
from l2r.protocol import SampleBatch

# Four steps: 0 goes on to 1; 1 is cut by the time limit (V of its final observation is 10); 2 goes
# on to 3; 3 terminates (its next value, 8, must not count).
REWARDS = np.array([1.0, 2.0, 3.0, 4.0])
VALUES = np.array([0.5, 1.0, 1.5, 2.0])
NEXT_VALUES = np.array([1.0, 10.0, 2.0, 8.0])
TERMINATED = np.array([0.0, 0.0, 0.0, 1.0])
ENDS = np.array([0.0, 1.0, 0.0, 1.0])


def test_gae_bootstraps_a_truncation_from_its_final_observation_and_a_termination_not_at_all():
    # deltas: 1 + .5*1 - .5 = 1; 2 + .5*10 - 1 = 6; 3 + .5*2 - 1.5 = 2.5; 4 - 2 = 2
    # advantages from the end, gamma * lambda = .25: 2; 2.5 + .25*2 = 3; 6 (ends); 1 + .25*6 = 2.5
    advantages = gae(REWARDS, VALUES, NEXT_VALUES, TERMINATED, ENDS, gamma=0.5, lam=0.5)
    np.testing.assert_allclose(advantages, [2.5, 6.0, 3.0, 2.0])


def test_vtrace_truncates_the_importance_ratios_and_cuts_traces_where_trajectories_end():
    # ratios 2, .5, 1, 1 -> rho = c = 1, .5, 1, 1 (clip 1, lambda 1, gamma .5)
    # rho * delta: 1*(1 + .5 - .5) = 1; .5*(2 + 5 - 1) = 3; 1*(3 + 1 - 1.5) = 2.5; 1*(4 - 2) = 2
    # v - V from the end, carry .5 * c where the trajectory goes on: 2; 2.5 + .5*2 = 3.5; 3; 1 + .5*3 = 2.5
    # advantages rho * (r + gamma * v' - V): 1 + .5*(1 + 3) - .5 = 2.5; .5*(2 + .5*10 - 1) = 3;
    #   3 + .5*(2 + 2) - 1.5 = 3.5; 4 - 2 = 2
    targets, advantages = vtrace(REWARDS, VALUES, NEXT_VALUES, TERMINATED, ENDS, np.log([2.0, 0.5, 1.0, 1.0]),
                                 gamma=0.5, lam=1.0, clip=1.0)
    np.testing.assert_allclose(targets, [3.0, 4.0, 5.0, 4.0])
    np.testing.assert_allclose(advantages, [2.5, 3.0, 3.5, 2.0])


def test_vtrace_targets_on_policy_are_the_gae_returns():
    targets, _ = vtrace(REWARDS, VALUES, NEXT_VALUES, TERMINATED, ENDS, np.zeros(4), gamma=0.5, lam=0.5, clip=1.0)
    np.testing.assert_allclose(targets, VALUES + gae(REWARDS, VALUES, NEXT_VALUES, TERMINATED, ENDS, 0.5, 0.5))


def test_clipped_surrogate_takes_the_pessimistic_term_and_stops_gradients_past_the_clip():
    old = torch.zeros(4)
    log_prob = torch.log(torch.tensor([1.5, 0.5, 1.1, 0.7])).requires_grad_()
    advantages = torch.tensor([1.0, 1.0, -1.0, -1.0])
    loss, ratio = clipped_surrogate(log_prob, old, advantages, clip=0.2)
    # max(-A r, -A clip(r)): max(-1.5, -1.2) = -1.2; max(-.5, -.8) = -.5; max(1.1, 1.1) = 1.1; max(.7, .8) = .8
    assert float(loss.detach()) == pytest.approx((-1.2 - 0.5 + 1.1 + 0.8) / 4)
    np.testing.assert_allclose(ratio.detach(), [1.5, 0.5, 1.1, 0.7], rtol=1e-6)
    loss.backward()
    # d/dlog_prob of -A r / 4 is -A r / 4 where the unclipped term counts, 0 where the clip holds it
    np.testing.assert_allclose(log_prob.grad, [0.0, -0.125, 0.275, 0.0], rtol=1e-5)


def test_clipped_surrogate_stays_finite_where_a_log_probability_moved_by_hundreds():
    # an action at the edge of (-1, 1), far from the policy's mean: its log-probability swings by hundreds
    log_prob = torch.tensor([-300.0, 200.0, 0.1], requires_grad=True)
    loss, ratio = clipped_surrogate(log_prob, torch.zeros(3), torch.tensor([-1.0, -1.0, 1.0]), clip=0.2)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(ratio).all() and torch.isfinite(log_prob.grad).all()
    assert log_prob.grad[1] == 0.0  # past the bound the sample gives no gradient


def sample_batch(n: int = 128, seed: int = 0, obs_dim: int = 5, act_dim: int = 3, rewards=None) -> SampleBatch:
    rng = np.random.default_rng(seed)
    return SampleBatch(
        0, n, False, rng.normal(size=(n, obs_dim)).astype(np.float32), rng.random((n, act_dim), dtype=np.float32),
        (rng.normal(size=n) if rewards is None else rewards).astype(np.float32),
        rng.normal(size=(n, obs_dim)).astype(np.float32), np.zeros(n, bool), np.zeros(n, bool),
        np.arange(n), np.arange(n), np.ones(n), np.zeros(n, np.int64),
        np.full(n, -3.0, np.float32), np.arange(n) % 16 == 15)


@pytest.mark.parametrize("lag_correction", LAG_CORRECTIONS)
def test_update_takes_epochs_times_minibatches_steps_with_finite_metrics(lag_correction):
    config = PPOConfig(batch_size=128, epochs=3, minibatches=4, hidden=(16, 16), lag_correction=lag_correction)
    state = init_state(config, 5, 3, seed=0)
    before = [p.detach().clone() for p in state.parameters()]
    metrics = update(state, batch_from_sample(sample_batch()), config)
    assert state.updates == 12
    assert all(torch.isfinite(value).all() for value in metrics.values()), metrics
    assert all(not torch.equal(old, new) for old, new in zip(before, state.parameters()) if old.numel() > 1)


def test_update_makes_actions_with_high_advantage_likelier():
    # Every step ends its episode, so its advantage is its reward minus its value: actions paid
    # +1 must gain probability, actions paid -1 lose it.
    n = 256
    rewards = np.where(np.arange(n) % 2 == 0, 1.0, -1.0)
    sample = sample_batch(n, rewards=rewards)
    sample.terminated[:] = True
    # the batch's log-probabilities are placeholders: take the data as on-policy
    config = PPOConfig(batch_size=n, epochs=4, minibatches=4, hidden=(32, 32), lr=1e-3, lag_correction="none")
    state = init_state(config, 5, 3, seed=1)
    batch = batch_from_sample(sample)
    with torch.no_grad():
        before = state.actor.evaluate(batch.obs, batch.action)[0]
    update(state, batch, config)
    with torch.no_grad():
        change = state.actor.evaluate(batch.obs, batch.action)[0] - before
    assert float(change[0::2].mean()) > 0 > float(change[1::2].mean())


def test_the_learner_computes_the_log_probability_the_actor_sent():
    # The ratio of a policy to itself must be 1: the actor's log-probability of the excitations it
    # sends equals the learner's of the same stored float32 excitations, near the edges too.
    config = PPOConfig(hidden=(16,))
    state = init_state(config, 5, 3, seed=2)
    with torch.no_grad():
        state.actor.head.weight.mul_(300.0)  # means far out: many excitations at 0 or 1 exactly
    obs = np.random.default_rng(3).normal(size=(512, 5)).astype(np.float32)
    excitations, log_probs = act_with_log_prob(state.actor, obs)
    assert ((excitations == 0) | (excitations == 1)).any()
    with torch.no_grad():
        learner = state.actor.evaluate(torch.from_numpy(obs), to_tanh_space(torch.from_numpy(excitations)))[0]
    np.testing.assert_allclose(learner.numpy(), log_probs, rtol=1e-5, atol=1e-4)


def test_a_queue_batch_ends_trajectories_at_episode_and_piece_ends():
    sample = sample_batch(8)
    sample.terminated[1], sample.truncated[4] = True, True
    sample.segment_ends[:] = False
    sample.segment_ends[6] = True
    batch: Batch = batch_from_sample(sample)
    assert batch.ends.tolist() == [0, 1, 0, 0, 1, 0, 1, 0]
    assert batch.terminated.tolist() == [0, 1, 0, 0, 0, 0, 0, 0]


def test_a_ppo_checkpoint_restores_its_state_and_a_sac_learner_refuses_it(tmp_path, capsys):
    config = PPOConfig(batch_size=128, epochs=1, minibatches=2, hidden=(16,))
    state = init_state(config, 41, 18, seed=0)
    update(state, batch_from_sample(sample_batch(obs_dim=41, act_dim=18)), config)
    save_checkpoint(checkpoint_path(tmp_path), state, config, 41, 18)
    saved = load_checkpoint(tmp_path)
    restored = saved.restore()
    assert (saved.algo, saved.config, restored.updates) == ("ppo", config, 2)
    assert all(torch.equal(a, b) for a, b in zip(state.parameters(), restored.parameters()))
    assert restored.optimizer.state_dict()["state"].keys() == state.optimizer.state_dict()["state"].keys()
    # Readers from before PPO take it for a policy checkpoint: l2r eval still runs its policy.
    assert torch.load(checkpoint_path(tmp_path), weights_only=True)["sac_config"] is None
    assert saved.policy().spec == state.actor.spec
    # Resuming needs the algorithm that trained it: one line, before any traffic.
    assert cli(["--run", "x", "--run-dir", str(tmp_path), "--resume", "--device", "cpu",
                "--connect", "tcp/127.0.0.1:9"]) == EXIT_CANNOT_START
    assert "holds PPO, not a SAC training state: use --algo ppo" in capsys.readouterr().err
