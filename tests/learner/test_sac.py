"""The SAC update on small networks: what each part of the algorithm must do."""

import copy
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from l2r.config import EXIT_CANNOT_START
from l2r.learner.__main__ import cli
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.sac import Batch, SACConfig, TwinCritic, batch_from_numpy, init_state, least_of_drawn, update
from l2r.policy import act, build_policy, default_spec, load_policy_state, policy_state

OBS, ACT = 5, 3


def small_config(**overrides) -> SACConfig:
    base = dict(hidden=(32, 32), batch_size=64, precision="float32", initial_alpha=0.1)
    return SACConfig(**(base | overrides))


def random_batch(n: int = 64, seed: int = 0, reward: float | None = None, terminated: float = 0.0) -> Batch:
    rng = np.random.default_rng(seed)
    rewards = rng.normal(size=n) if reward is None else np.full(n, reward)
    return batch_from_numpy(rng.normal(size=(n, OBS)), rng.random((n, ACT)), rewards, rng.normal(size=(n, OBS)),
                            np.full(n, terminated))


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
@pytest.mark.parametrize("layer_norm", [True, False])
def test_update_gives_finite_metrics_and_moves_every_network(precision, layer_norm):
    config = small_config(precision=precision, layer_norm=layer_norm)
    state = init_state(config, OBS, ACT, seed=0)
    before = copy.deepcopy([state.actor.state_dict(), state.critic.state_dict(), state.target_critic.state_dict()])
    metrics = update(state, random_batch(), config)
    for name, value in metrics.items():
        assert torch.isfinite(value).all(), name
    assert metrics["priorities"].shape == (64,)
    after = [state.actor.state_dict(), state.critic.state_dict(), state.target_critic.state_dict()]
    for old, new in zip(before, after):
        assert any(not torch.equal(old[k], new[k]) for k in old)


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_critic_learns_the_value_of_a_constant_reward(precision):
    # Every step pays 1 and every episode ends at once: Q = reward_scale * 1 everywhere.
    config = small_config(precision=precision, reward_scale=2.0, critic_lr=3e-3, tau=0.05)
    state = init_state(config, OBS, ACT, seed=1)
    for step in range(100):
        metrics = update(state, random_batch(seed=step, reward=1.0, terminated=1.0), config)
    assert float(metrics["q_mean"]) == pytest.approx(2.0, abs=0.05)


def test_soft_bellman_target_bootstraps_with_the_entropy_bonus_unless_terminated():
    config = small_config(gamma=0.5, reward_scale=1.0, initial_alpha=0.5)
    state = init_state(config, OBS, ACT, seed=2)
    with torch.no_grad():  # a critic whose every output is 10: last layer zero, bias 10
        for target in (state.critic, state.target_critic):
            target.weights[-1].zero_()
            target.biases[-1].fill_(10.0)
    terminal = update(copy.deepcopy(state), random_batch(reward=1.0, terminated=1.0), config)
    assert float(terminal["target_mean"]) == pytest.approx(1.0, rel=1e-6)

    # Record what the policy samples inside the update: its first draw is a' ~ pi(.|s') for the target
    # (of s' as the networks see it: unfiltered here).
    bootstrapped, batch, draws = copy.deepcopy(state), random_batch(reward=1.0, terminated=0.0), []
    sample = bootstrapped.actor.sample_of
    bootstrapped.actor.sample_of = lambda seen: draws.append((seen, sample(seen))) or draws[-1][1]
    truncated = update(bootstrapped, batch, config)
    next_obs, (_, next_log_prob) = draws[0]
    assert torch.equal(next_obs, batch.next_obs)
    # r + gamma * (Q(s', a') - alpha * log pi(a'|s')), averaged over the batch.
    entropy_term = 0.5 * 0.5 * float(next_log_prob.mean())
    expected = 1.0 + 0.5 * 10.0 - entropy_term
    assert abs(entropy_term) > 0.01, "the entropy term must matter at the tolerance below"
    assert float(truncated["target_mean"]) == pytest.approx(expected, rel=1e-5)


def test_an_n_step_batch_bootstraps_with_its_own_discounts():
    # Critics of 10 everywhere and a temperature of almost 0: each sample's target is its reward plus
    # its discount times 10, whatever the policy draws.
    config = small_config(n_step=3, gamma=0.9, reward_scale=2.0, initial_alpha=1e-9, autotune_alpha=False)
    state = init_state(config, OBS, ACT, seed=3)
    constant_critics(state, [10.0, 10.0])
    # Windows of 3 steps, one ended by a termination (discount 0), one cut short after 2 steps by the
    # end of the data (gamma^2): the replay gives each sample its discount.
    discounts = np.array([0.9 ** 3, 0.0, 0.9 ** 2, 0.9 ** 3], np.float32)
    rng = np.random.default_rng(4)
    batch = batch_from_numpy(rng.normal(size=(4, OBS)), rng.random((4, ACT)), np.full(4, 0.5),
                             rng.normal(size=(4, OBS)), np.array([0.0, 1.0, 0.0, 0.0]), discounts=discounts)
    metrics = update(state, batch, config)
    expected = 2.0 * 0.5 + 10.0 * discounts
    assert float(metrics["target_mean"]) == pytest.approx(float(expected.mean()), rel=1e-5)
    # SAC's one-step discount, gamma * (1 - terminated), would have given 1 + 9 for three of the four.
    assert float(metrics["target_mean"]) != pytest.approx(1.0 + 9.0 * 3 / 4, rel=1e-3)


def constant_critics(state, values) -> None:
    """Make critic i output values[i] everywhere (last layer zero, bias the value), online and target."""
    with torch.no_grad():
        for critic in (state.critic, state.target_critic):
            critic.weights[-1].zero_()
            critic.biases[-1].copy_(torch.tensor(values, dtype=torch.float32).reshape(-1, 1, 1))


def test_an_ensemble_trains_every_critic_towards_the_least_of_the_drawn_ones():
    everyone = small_config(critics=4, critics_in_min=4, gamma=0.5, reward_scale=1.0, initial_alpha=1e-9,
                            autotune_alpha=False)
    state = init_state(everyone, OBS, ACT, seed=2)
    assert state.critic.weights[0].shape[0] == 4 and state.target_critic.weights[0].shape[0] == 4
    trained = copy.deepcopy(state)
    update(trained, random_batch(), everyone)
    assert all(not torch.equal(old[i], new[i]) for old, new in zip(state.critic.weights, trained.critic.weights)
               for i in range(4))
    constant_critics(state, [10.0, 20.0, 30.0, 40.0])
    metrics = update(copy.deepcopy(state), random_batch(reward=1.0), everyone)
    assert float(metrics["target_mean"]) == pytest.approx(1.0 + 0.5 * 10.0, rel=1e-5)  # r + gamma * least of all

    # One drawn at a time: each update's target bootstraps from one critic, a different one from draw to draw.
    one = replace(everyone, critics_in_min=1)
    targets = {round(float(update(copy.deepcopy(state), random_batch(reward=1.0), one)["target_mean"]), 3)
               for _ in range(40)}
    assert targets == {6.0, 11.0, 16.0, 21.0}


def test_least_of_drawn_takes_the_least_of_a_random_subset():
    q = torch.tensor([[3.0, 0.0], [1.0, 5.0], [2.0, 9.0]])  # (critics, batch)
    assert least_of_drawn(q, small_config(critics=3, critics_in_min=3)).tolist() == [1.0, 0.0]
    pairs = {tuple(least_of_drawn(q, small_config(critics=3, critics_in_min=2)).tolist()) for _ in range(60)}
    assert pairs == {(1.0, 0.0), (2.0, 0.0), (1.0, 5.0)}  # the least of each of the three pairs


def test_target_critics_follow_by_polyak_averaging():
    config = small_config(tau=0.25)
    state = init_state(config, OBS, ACT, seed=3)
    old_target = copy.deepcopy(state.target_critic.state_dict())
    update(state, random_batch(), config)
    for name, online in state.critic.state_dict().items():
        expected = 0.75 * old_target[name] + 0.25 * online
        torch.testing.assert_close(state.target_critic.state_dict()[name], expected)


def test_alpha_rises_when_entropy_is_below_target_and_falls_above():
    high = small_config(target_entropy=50.0)  # far above what 3 squashed dims can reach
    low = small_config(target_entropy=-50.0)
    for config, direction in ((high, 1), (low, -1)):
        state = init_state(config, OBS, ACT, seed=4)
        for step in range(5):
            update(state, random_batch(seed=step), config)
        assert direction * (float(state.log_alpha.detach()) - math.log(0.1)) > 0


def test_alpha_falls_no_lower_than_its_floor():
    floored = small_config(target_entropy=-50.0, alpha_lr=0.1, min_alpha=0.08)
    unfloored = replace(floored, min_alpha=0.0)
    floored_state, unfloored_state = init_state(floored, OBS, ACT, seed=4), init_state(unfloored, OBS, ACT, seed=4)
    for step in range(5):
        update(floored_state, random_batch(seed=step), floored)
        update(unfloored_state, random_batch(seed=step), unfloored)
    assert float(unfloored_state.log_alpha.detach().exp()) < 0.07
    assert float(floored_state.log_alpha.detach().exp()) == pytest.approx(0.08)
    with pytest.raises(ValueError, match="min_alpha"):
        small_config(min_alpha=0.2)


def test_fixed_alpha_stays():
    config = small_config(autotune_alpha=False)
    state = init_state(config, OBS, ACT, seed=5)
    update(state, random_batch(), config)
    assert float(state.log_alpha.detach().exp()) == pytest.approx(0.1)


def test_priorities_are_absolute_td_errors_and_weights_scale_the_critic_loss():
    config = small_config()
    state = init_state(config, OBS, ACT, seed=6)
    batch = random_batch()
    torch.manual_seed(0)
    uniform = update(copy.deepcopy(state), batch, config)
    batch.weights = torch.full((64,), 0.5)
    torch.manual_seed(0)
    halved = update(copy.deepcopy(state), batch, config)
    assert (uniform["priorities"] >= 0).all()
    torch.testing.assert_close(halved["critic_loss"], uniform["critic_loss"] * 0.5)
    # Zero weight on a sample removes it from the critic loss.
    batch.weights = torch.zeros(64)
    assert float(update(copy.deepcopy(state), batch, config)["critic_loss"]) == 0.0


def test_twin_critic_equals_two_separate_networks():
    critic = TwinCritic(OBS, ACT, (16, 16), "elu", layer_norm=True)
    obs, action = torch.randn(7, OBS), torch.randn(7, ACT)
    q = critic(obs, action)
    for i in range(2):
        x = torch.cat([obs, action], -1)
        for layer in range(2):
            x = x @ critic.weights[layer][i] + critic.biases[layer][i]
            x = torch.nn.functional.layer_norm(x, (16,)) * critic.norm_scales[layer][i] + critic.norm_shifts[layer][i]
            x = torch.nn.functional.elu(x)
        torch.testing.assert_close(q[i], (x @ critic.weights[2][i] + critic.biases[2][i]).squeeze(-1))


def test_policy_acts_in_unit_box_and_weights_round_trip():
    spec = default_spec(OBS, ACT) | {"hidden": [16, 16]}
    policy, copy_ = build_policy(spec), build_policy(spec)
    obs = np.random.default_rng(0).normal(size=(10, OBS)) * 100
    actions = act(policy, obs)
    assert actions.shape == (10, ACT) and actions.dtype == np.float32
    assert (actions >= 0).all() and (actions <= 1).all()
    load_policy_state(copy_, policy_state(policy))
    np.testing.assert_array_equal(act(policy, obs, deterministic=True), copy_.act(obs, deterministic=True))
    bad = policy_state(policy)
    bad["head.weight"] = bad["head.weight"][:, :3]
    with pytest.raises(ValueError, match="head.weight"):
        load_policy_state(copy_, bad)


def test_log_prob_matches_the_change_of_variables():
    policy = build_policy(default_spec(OBS, ACT) | {"hidden": [8]})
    obs = torch.randn(4, OBS)
    torch.manual_seed(0)
    action, log_prob = policy.sample_of(policy.embed(obs))
    mean, log_std = policy(obs)
    pre_tanh = torch.atanh(action.clamp(-0.999999, 0.999999))
    gauss = torch.distributions.Normal(mean, log_std.exp()).log_prob(pre_tanh)
    expected = (gauss - torch.log1p(-action.pow(2) + 1e-12)).sum(-1)
    torch.testing.assert_close(log_prob, expected, rtol=1e-3, atol=1e-3)


def test_auto_precision_is_float32_on_cuda_even_where_it_has_bfloat16(monkeypatch):
    """A GPU update of these networks waits on kernel launches; autocast's casts only add more."""
    from l2r.learner.common import bfloat16_pays

    monkeypatch.setattr(torch.cuda, "is_bf16_supported", lambda *args, **kwargs: True)
    assert not bfloat16_pays(torch.device("cuda"))
    assert bfloat16_pays(torch.device("cpu")) == torch.ops.mkldnn._is_mkldnn_bf16_supported()


def test_an_ensembles_checkpoint_restores_every_critic_and_a_learner_of_other_critics_refuses_it(tmp_path, capsys):
    config = small_config(critics=5, critics_in_min=2)
    state = init_state(config, OBS, ACT, seed=7)
    update(state, random_batch(), config)
    save_checkpoint(checkpoint_path(tmp_path), state, config, OBS, ACT)
    saved = load_checkpoint(tmp_path)
    assert saved.config == config
    assert all(torch.equal(a, b) for a, b in zip(state.critic.parameters(), saved.restore().critic.parameters()))
    argv = ["--run", "x", "--run-dir", str(tmp_path), "--resume", "--device", "cpu", "--obs-dim", str(OBS),
            "--act-dim", str(ACT), "--hidden", "32,32", "--connect", "tcp/127.0.0.1:9"]
    assert cli(argv) == EXIT_CANNOT_START
    assert "holds 5 critics, the settings ask for 2: use the same --critics" in capsys.readouterr().err
