"""The TD3 update on small networks against targets computed by hand, its exploration schedule, the
deterministic policy as actors build it, checkpoints and the command line."""

import copy
import math
from dataclasses import replace

import numpy as np
import pytest
import torch

from l2r.config import EXIT_CANNOT_START
from l2r.actors.actor import run_deterministic
from l2r.learner.__main__ import cli, parse_settings
from l2r.learner.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from l2r.learner.daemon import Meter
from l2r.learner.sac import SACConfig, batch_from_numpy
from l2r.learner.sac import init_state as init_sac_state
from l2r.learner.steps import GradientSteps
from l2r.learner.td3 import TD3Config, exploration_std, follow_exploration_schedule, init_state, update
from l2r.policy import (
    DeterministicPolicy, Policy, act, act_with_log_prob, build_policy, check_spec, load_policy_state, policy_state,
    to_excitation,
)
from l2r.protocol import Weights, decode, encode
from tests.actors.standin import StandIn

OBS, ACT = 5, 3


def small_config(**overrides) -> TD3Config:
    base = dict(hidden=(32, 32), batch_size=64, precision="float32")
    return TD3Config(**(base | overrides))


def train_step(state, batch, config: TD3Config) -> dict[str, torch.Tensor]:
    """One update as the learner takes it: counted, its actor step decided by the count, the
    exploration std set after it."""
    metrics = GradientSteps(update, config, policy_delay=config.policy_delay)(state, batch)
    follow_exploration_schedule(state, config)
    return metrics


def random_batch(n: int = 64, seed: int = 0, terminated=0.0, discounts=None):
    rng = np.random.default_rng(seed)
    return batch_from_numpy(rng.normal(size=(n, OBS)), rng.random((n, ACT)), rng.normal(size=n),
                            rng.normal(size=(n, OBS)), np.broadcast_to(terminated, n), discounts=discounts)


def hand_target(state, batch, config, discount: torch.Tensor) -> torch.Tensor:
    """y = reward_scale * R + discount * min(Q1', Q2')(s', pi'(s')), without smoothing noise."""
    with torch.no_grad():
        next_q = state.target_critic(state.actor.observation_filter(batch.next_obs), state.target_actor(batch.next_obs))
        return config.reward_scale * batch.reward + discount * next_q.min(0).values


def priorities_for(state, batch, target: torch.Tensor) -> torch.Tensor:
    """|Q_i(s, a) - y| averaged over the critics, as the update reports it."""
    with torch.no_grad():
        return (state.critic(state.actor.observation_filter(batch.obs), batch.action) - target).abs().mean(0)


@pytest.mark.parametrize("precision", ["float32", "bfloat16"])
def test_two_updates_give_finite_metrics_and_move_every_network(precision):
    config = small_config(precision=precision)
    state = init_state(config, OBS, ACT, seed=0)
    networks = ("actor", "critic", "target_actor", "target_critic")
    before = {name: copy.deepcopy(getattr(state, name).state_dict()) for name in networks}
    for step in range(2):
        metrics = train_step(state, random_batch(seed=step), config)
    assert {"critic_loss", "actor_loss", "q_mean", "target_mean", "exploration_std"} <= set(metrics)
    for name, value in metrics.items():
        assert torch.isfinite(value).all(), name
    assert metrics["priorities"].shape == (64,)
    for name in networks:
        after = getattr(state, name).state_dict()
        assert any(not torch.equal(before[name][k], after[k]) for k in after), name
    assert state.updates == 2


def trained_state(config: TD3Config, seed: int):
    """A state a few updates in, its target networks well apart from the online ones (tau 0.5)."""
    state = init_state(replace(config, tau=0.5, policy_delay=1), OBS, ACT, seed=seed)
    for step in range(4):
        train_step(state, random_batch(seed=100 + step), replace(config, tau=0.5, policy_delay=1))
    return state


def test_the_n_step_target_bootstraps_with_the_batch_s_discounts():
    config = small_config(gamma=0.9, reward_scale=2.0, target_noise=0.0, n_step=3)
    state = trained_state(config, seed=1)
    # Sums of 3 discounted rewards; a window that ended in a termination (discount 0); a window cut
    # short by the end of an episode's data after 2 steps (gamma^2).
    discounts = np.array([0.9 ** 3, 0.0, 0.9 ** 2, 0.9 ** 3], np.float32)
    batch = random_batch(n=4, seed=2, terminated=np.array([0.0, 1.0, 0.0, 0.0]), discounts=discounts)
    expected = hand_target(state, batch, config, torch.as_tensor(discounts))
    expected_priorities = priorities_for(state, batch, expected)
    metrics = train_step(state, batch, config)
    torch.testing.assert_close(metrics["target_mean"], expected.mean())
    torch.testing.assert_close(metrics["priorities"], expected_priorities)
    # gamma * (1 - terminated) would have bootstrapped the second sample and discounted the rest by 0.9.
    one_step = hand_target(state, batch, config, 0.9 * (1.0 - batch.terminated))
    assert not torch.allclose(priorities_for(state, batch, one_step), expected_priorities, atol=1e-3)


def test_the_one_step_target_is_cut_by_a_termination_only():
    config = small_config(gamma=0.5, reward_scale=3.0, target_noise=0.0)
    state = trained_state(config, seed=3)
    batch = random_batch(n=6, seed=4, terminated=np.array([1.0, 0.0, 1.0, 0.0, 0.0, 1.0]))
    expected = hand_target(state, batch, config, 0.5 * (1.0 - batch.terminated))
    expected_priorities = priorities_for(state, batch, expected)
    metrics = train_step(state, batch, config)
    torch.testing.assert_close(metrics["priorities"], expected_priorities)
    torch.testing.assert_close(metrics["target_mean"], expected.mean())


def recorded_target_actions(config: TD3Config, target_action: float, n: int = 512,
                            online_action: float = 0.0) -> torch.Tensor:
    """The actions the target critics are asked about in one update, the target policy's every output
    being `target_action` and the online policy's `online_action`."""
    state = init_state(config, OBS, ACT, seed=5)
    with torch.no_grad():
        for policy, action in ((state.target_actor, target_action), (state.actor, online_action)):
            policy.head.weight.zero_()
            policy.head.bias.fill_(math.atanh(action))
    seen = []
    forward = state.target_critic.forward
    state.target_critic.forward = lambda obs, action, **kw: seen.append(action) or forward(obs, action, **kw)
    train_step(state, random_batch(n=n, seed=6), config)
    (actions,) = seen
    return actions


def test_target_smoothing_noise_is_clipped_at_noise_clip_and_the_action_at_the_bounds():
    # A std of 100 puts nearly every draw past the clip: the noise lands on +-0.3 exactly.
    actions = recorded_target_actions(small_config(target_noise=100.0, noise_clip=0.3), target_action=0.0)
    assert actions.abs().max() <= 0.3 + 1e-6
    assert (actions.abs() > 0.3 - 1e-6).float().mean() > 0.9
    # Around 0.9 the upper side meets the action bound first: actions in [0.6, 1], many exactly 1.
    actions = recorded_target_actions(small_config(target_noise=100.0, noise_clip=0.3), target_action=0.9)
    assert actions.min() >= 0.6 - 1e-6 and actions.max() == 1.0 and (actions == 1.0).float().mean() > 0.4


def test_target_noise_none_takes_the_scheduled_exploration_std():
    config = small_config(target_noise=None, noise_clip=1.0, exploration_std_start=0.05, exploration_std_end=0.05)
    actions = recorded_target_actions(config, target_action=0.0, n=2048)
    assert float(actions.std()) == pytest.approx(0.05, rel=0.05)
    assert float(actions.mean()) == pytest.approx(0.0, abs=0.01)


@pytest.mark.parametrize("online", [False, True])
def test_the_target_action_is_the_polyak_copy_s_or_if_asked_the_online_actor_s(online):
    actions = recorded_target_actions(small_config(target_noise=0.0, online_target_actor=online), target_action=-0.5,
                                      online_action=0.5)
    torch.testing.assert_close(actions, torch.full_like(actions, 0.5 if online else -0.5))


def test_the_exploration_schedule_is_linear_then_constant_and_the_weights_carry_it():
    config = small_config(exploration_std_start=1.0, exploration_std_end=0.2, exploration_std_updates=8)
    # 1.0 - (0.8 / 8) * k for k up to 8, then 0.2
    expected = {0: 1.0, 2: 0.8, 4: 0.6, 6: 0.4, 8: 0.2, 9: 0.2, 1000: 0.2}
    for updates, std in expected.items():
        assert exploration_std(config, updates) == pytest.approx(std)
    assert exploration_std(small_config(exploration_std_updates=0, exploration_std_start=1.0), 0) == 0.1
    state = init_state(config, OBS, ACT, seed=7)
    for updates in range(11):
        published = policy_state(state.actor)["exploration_std"]  # what WeightsOutlet sends
        assert float(published) == pytest.approx(exploration_std(config, updates)), updates
        metrics = train_step(state, random_batch(seed=updates), config)
        assert float(metrics["exploration_std"]) == pytest.approx(exploration_std(config, updates)), updates


def test_the_actor_and_the_targets_move_on_every_policy_delay_th_update_only():
    config = small_config(policy_delay=3)
    state = init_state(config, OBS, ACT, seed=8)
    networks = {name: getattr(state, name) for name in ("actor", "critic", "target_actor", "target_critic")}
    for updates in range(1, 7):
        before = {name: [p.detach().clone() for p in net.parameters()] for name, net in networks.items()}
        metrics = train_step(state, random_batch(seed=updates), config)
        moved = {name: any(not torch.equal(old, new) for old, new in zip(before[name], net.parameters()))
                 for name, net in networks.items()}
        delayed = updates % 3 == 0
        assert moved == {"actor": delayed, "critic": True, "target_actor": delayed, "target_critic": delayed}, updates
        assert ("actor_loss" in metrics) == delayed


def test_with_several_updates_a_batch_the_actor_steps_on_every_policy_delay_th_update_of_the_run():
    config = small_config(policy_delay=3, update_repeat=2)
    state = init_state(config, OBS, ACT, seed=14)
    state.updates = 1  # as resumed: the delay counts over the run, not from this process's start
    actor_moved = []

    def recorded(state, batch, config, actor_step, actor_learns):
        before = [p.detach().clone() for p in state.actor.parameters()]
        metrics = update(state, batch, config, actor_step, actor_learns)
        actor_moved.append(any(not torch.equal(old, new) for old, new in zip(before, state.actor.parameters())))
        return metrics

    steps = GradientSteps(recorded, config, repeat=config.update_repeat, policy_delay=config.policy_delay)
    for call in range(5):
        steps(state, random_batch(seed=call))
        assert state.updates == 1 + 2 * (call + 1)
    assert actor_moved == [index % 3 == 0 for index in range(2, 12)]


def test_in_the_critic_warm_up_the_actor_holds_still_while_the_critics_and_their_targets_learn():
    config = small_config(policy_delay=2, critic_warmup=4)
    state = init_state(config, OBS, ACT, seed=14)
    steps = GradientSteps(update, config, policy_delay=config.policy_delay, actor_after=config.critic_warmup)
    actor, targets = copy.deepcopy(state.actor), copy.deepcopy([state.target_actor, state.target_critic])
    critic = copy.deepcopy(state.critic)
    for call in range(4):
        metrics = steps(state, random_batch(seed=20 + call))
        assert "actor_loss" not in metrics
    assert all(torch.equal(a, b) for a, b in zip(actor.parameters(), state.actor.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(critic.parameters(), state.critic.parameters()))
    assert any(not torch.equal(a, b) for a, b in zip(targets[1].parameters(), state.target_critic.parameters()))
    for call in range(2):  # the 6th update is an actor step of the delay: the actor learns from then on
        metrics = steps(state, random_batch(seed=30 + call))
    assert "actor_loss" in metrics
    assert any(not torch.equal(a, b) for a, b in zip(actor.parameters(), state.actor.parameters()))


def test_the_actor_loss_is_minus_q1_of_its_own_action_against_the_updated_critics():
    config = small_config(policy_delay=1)
    state = trained_state(config, seed=12)
    actor_before, batch = copy.deepcopy(state.actor), random_batch(seed=13)
    metrics = train_step(state, batch, config)
    with torch.no_grad():  # the critic step came first; the actor step changes no critic
        q = state.critic(state.actor.observation_filter(batch.obs), actor_before(batch.obs))
    torch.testing.assert_close(metrics["actor_loss"], -q[0].mean())
    assert not torch.allclose(q[0].mean(), q.min(0).values.mean(), atol=1e-3), "Q1 and min(Q1, Q2) must differ here"


def actor_step_actions(state, batch, config: TD3Config) -> tuple[dict, torch.Tensor]:
    """One update's metrics and the actions the actor's loss asked the critics about."""
    seen = []
    forward = state.critic.forward
    state.critic.forward = lambda obs, action, **kw: (kw.get("detach_weights") and seen.append(action.detach())) \
        or forward(obs, action, **kw)
    metrics = train_step(state, batch, config)
    (actions,) = seen
    return metrics, actions


def test_the_min_noisy_actor_loss_is_minus_the_lower_critic_at_the_noisy_action():
    config = small_config(policy_delay=1, actor_loss="min-noisy", exploration_std_start=100.0,
                          exploration_std_end=100.0, noise_clip=0.3)
    state = trained_state(config, seed=12)
    actor_before, batch = copy.deepcopy(state.actor), random_batch(seed=13)
    metrics, noisy = actor_step_actions(state, batch, config)
    with torch.no_grad():  # the critic step came first; the actor step changes no critic
        own = actor_before(batch.obs)
        q = state.critic(state.actor.observation_filter(batch.obs), noisy)
    torch.testing.assert_close(metrics["actor_loss"], -q.min(0).values.mean())
    # A std of 100 puts nearly every draw past the clip, and the action stays within its bounds.
    assert noisy.abs().max() <= 1.0
    shift = noisy - own
    assert shift.abs().max() <= 0.3 + 1e-6
    assert ((shift.abs() - 0.3).abs() < 1e-5).float().mean() > 0.8


def test_the_min_noisy_actor_learns_through_noisy_actions_held_at_the_bounds():
    # Noise clipped at 5 with a std of 1e6: every noisy action lies past a bound and is held there;
    # the actor's gradient goes through the hold as if it were not there (DrQ-v2's), not zero.
    config = small_config(policy_delay=1, actor_loss="min-noisy", exploration_std_start=1e6,
                          exploration_std_end=1e6, noise_clip=5.0)
    state = trained_state(replace(config, exploration_std_start=0.1, exploration_std_end=0.1), seed=12)
    follow_exploration_schedule(state, config)
    _, noisy = actor_step_actions(state, random_batch(seed=13), config)
    assert torch.equal(noisy.abs(), torch.ones_like(noisy))
    assert state.actor.head.weight.grad.abs().sum() > 0  # (what the actor's step took)


def test_targets_follow_by_polyak_averaging_on_actor_updates():
    config = small_config(tau=0.25, policy_delay=1)
    state = init_state(config, OBS, ACT, seed=9)
    old = [copy.deepcopy(m.state_dict()) for m in (state.target_actor, state.target_critic)]
    train_step(state, random_batch(), config)
    for target, online, before in zip((state.target_actor, state.target_critic), (state.actor, state.critic), old):
        for name, value in online.named_parameters():
            torch.testing.assert_close(target.state_dict()[name], 0.75 * before[name] + 0.25 * value.detach())


def test_a_checkpoint_restores_training_exactly_and_eval_reads_its_policy(tmp_path):
    config = small_config(exploration_std_start=1.0, exploration_std_end=0.1, exploration_std_updates=10,
                          normalize_obs=True, target_noise=None)
    state = init_state(config, OBS, ACT, seed=10)
    for step in range(3):
        train_step(state, random_batch(seed=step), config)
    state.version, state.extra = 4, {"samples": 192}
    save_checkpoint(checkpoint_path(tmp_path), state, config, OBS, ACT)
    actor_as_saved = copy.deepcopy(state.actor).eval()

    saved = load_checkpoint(tmp_path)
    assert (saved.algo, saved.config, saved.version, saved.updates) == ("td3", config, 4, 3)
    assert torch.load(checkpoint_path(tmp_path), weights_only=True)["sac_config"] is None
    restored = saved.restore()
    assert restored.extra == {"samples": 192}
    assert restored.target_actor.observation_filter is restored.actor.observation_filter
    for step in (3, 4):  # update 4 is an actor update
        torch.manual_seed(step)
        metrics_a = train_step(state, random_batch(seed=step), config)
        torch.manual_seed(step)
        metrics_b = train_step(restored, random_batch(seed=step), config)
        for name in metrics_a:  # networks, targets, optimizer moments, statistics, schedule: the same step
            torch.testing.assert_close(metrics_a[name], metrics_b[name], rtol=0, atol=0)
    for a, b in zip(state.parameters(), restored.parameters()):
        assert torch.equal(a, b)

    policy = load_checkpoint(tmp_path).policy()  # what l2r eval acts with
    assert isinstance(policy, DeterministicPolicy) and policy.spec["kind"] == "deterministic"
    obs = np.random.default_rng(1).normal(size=(4, OBS))
    np.testing.assert_array_equal(act(policy, obs, True), act(actor_as_saved, obs, True))


def test_a_td3_learner_refuses_a_sac_checkpoint_and_a_sac_learner_a_td3_one(tmp_path, capsys):
    sac_config = SACConfig(hidden=(16,), precision="float32")
    save_checkpoint(checkpoint_path(tmp_path / "sac"), init_sac_state(sac_config, 41, 18), sac_config, 41, 18)
    td3_config = small_config(hidden=(16,))
    save_checkpoint(checkpoint_path(tmp_path / "td3"), init_state(td3_config, 41, 18), td3_config, 41, 18)
    for run_dir, algo, message in (("sac", "td3", "holds SAC, not a TD3 training state: use --algo sac"),
                                   ("td3", "sac", "holds TD3, not a SAC training state: use --algo td3")):
        # Fails before any network traffic, so the endpoint need not exist.
        assert cli(["--run", "x", "--run-dir", str(tmp_path / run_dir), "--resume", "--device", "cpu",
                    "--algo", algo, "--connect", "tcp/127.0.0.1:9"]) == EXIT_CANNOT_START
        assert message in capsys.readouterr().err


def test_the_policy_an_actor_builds_from_the_weights_explores_within_bounds_and_acts_deterministically_if_asked():
    config = small_config(exploration_std_start=0.5, exploration_std_end=0.5)
    state = init_state(config, 41, 18, seed=11)  # the stand-in env's widths
    message = decode(encode(Weights(3, policy_state(state.actor), dict(state.actor.spec))), Weights)
    policy = build_policy(message.spec)  # as l2r.actors.weights does
    load_policy_state(policy, {k: np.array(v) for k, v in message.params.items()})
    assert isinstance(policy, DeterministicPolicy) and float(policy.exploration_std) == 0.5

    obs = np.random.default_rng(2).normal(size=(256, 41)).astype(np.float32)
    mean = to_excitation(state.actor(torch.as_tensor(obs))).detach().numpy()
    np.testing.assert_allclose(act(policy, obs, deterministic=True), mean, atol=1e-6)
    np.testing.assert_array_equal(act(policy, obs, deterministic=True), act(policy, obs, deterministic=True))

    actions, log_probs = act_with_log_prob(policy, obs)  # what an actor sends
    assert actions.dtype == np.float32 and ((0 <= actions) & (actions <= 1)).all()
    assert (log_probs == 0).all() and log_probs.shape == (256,)
    assert ((actions == 0) | (actions == 1)).any(), "a std of 0.5 must push some actions onto the bounds"
    with torch.no_grad():
        policy.exploration_std.fill_(0.05)  # so small that no action reaches a bound
    noise = 2 * (act(policy, obs) - mean)  # in the policy's (-1, 1) space
    assert float(noise.std()) == pytest.approx(0.05, rel=0.05) and abs(float(noise.mean())) < 0.005
    with torch.no_grad():
        policy.exploration_std.fill_(0.0)
    np.testing.assert_allclose(act(policy, obs), act(policy, obs, deterministic=True), atol=1e-6)

    # An evaluator's and l2r eval's deterministic episodes: the same twice.
    first = run_deterministic(policy, [StandIn(length=5), StandIn(length=5)], [0, 1])
    assert first == run_deterministic(policy, [StandIn(length=5), StandIn(length=5)], [0, 1])


def test_a_spec_without_a_kind_is_a_gaussian_policy_and_a_bad_kind_is_refused():
    old = {"obs_dim": OBS, "act_dim": ACT, "hidden": [8], "activation": "elu", "layer_norm": True}
    assert check_spec(old)["kind"] == "gaussian"
    policy = build_policy(old)
    assert type(policy) is Policy
    assert policy_state(policy)["head.weight"].shape == (2 * ACT, 8)
    assert type(build_policy(old | {"kind": "deterministic"})) is DeterministicPolicy
    for kind in ("greedy", ["deterministic"], None):
        with pytest.raises(ValueError, match="kind"):
            check_spec(old | {"kind": kind})
    with pytest.raises(ValueError, match="deterministic spec"):
        Policy(old | {"kind": "deterministic"})


def residual_batch(n: int = 64, seed: int = 0):
    """A random batch whose observations hold, at [1, 1 + ACT), last actions in (-1, 1)."""
    batch = random_batch(n=n, seed=seed)
    for obs in (batch.obs, batch.next_obs):
        obs[:, 1:1 + ACT] = torch.tanh(obs[:, 1:1 + ACT])
    return batch


def test_a_residual_policy_changes_the_last_action_the_state_holds_and_repeats_it_where_its_head_gives_0():
    spec = {"obs_dim": OBS, "act_dim": ACT, "hidden": [8], "activation": "elu", "layer_norm": True,
            "kind": "residual", "residual": 1}
    policy = build_policy(spec)
    assert isinstance(policy, DeterministicPolicy) and policy.spec["residual"] == 1
    obs = residual_batch(n=16).obs
    last = obs[:, 1:1 + ACT]
    with torch.no_grad():
        head = policy.head_output(obs)
        torch.testing.assert_close(policy(obs), torch.tanh(torch.atanh(last) + head))
        policy.head.weight.zero_()
        policy.head.bias.zero_()
        torch.testing.assert_close(policy(obs), last)
        at_bounds = obs.clone()
        at_bounds[:, 1:1 + ACT] = torch.tensor([-1.0, 1.0, 0.0])
        assert torch.isfinite(policy(at_bounds)).all() and policy(at_bounds).abs().max() < 1.0
    for bad, message in ((spec | {"residual": OBS - ACT + 1}, "index from 0 to 2"),
                         (spec | {"residual": 1.0}, "index from 0 to 2"),
                         ({k: v for k, v in spec.items() if k != "residual"}, "index from 0 to 2"),
                         (spec | {"kind": "deterministic"}, "for the residual kind, not deterministic"),
                         (spec | {"frame_stack": 2}, "from one float32 state")):
        with pytest.raises(ValueError, match=message):
            check_spec(bad)


def test_td3_trains_a_residual_actor_and_targets_on_the_last_actions_of_their_own_observations():
    config = small_config(residual=1, policy_delay=1, target_noise=0.0, gamma=0.5)
    state = init_state(config, OBS, ACT, seed=20)
    assert state.actor.spec["kind"] == "residual" and state.target_actor.spec["residual"] == 1
    batch = residual_batch(seed=21)
    expected = hand_target(state, batch, config, 0.5 * (1.0 - batch.terminated))  # the target's from next_obs
    actor_before = copy.deepcopy(state.actor)
    metrics, actions = actor_step_actions(state, batch, config)
    torch.testing.assert_close(metrics["target_mean"], expected.mean())
    with torch.no_grad():
        torch.testing.assert_close(actions, actor_before(batch.obs))


def test_the_command_line_builds_td3_s_settings():
    config = parse_settings(["--algo", "td3", "--n-step", "3", "--policy-delay", "4", "--noise-clip", "0.3",
                             "--exploration-std-start", "1.0", "--exploration-std-updates", "500", "--hidden", "64,64",
                             "--mirror"]).algorithm()
    assert config == TD3Config(n_step=3, policy_delay=4, noise_clip=0.3, exploration_std_start=1.0,
                               exploration_std_updates=500, hidden=(64, 64), mirror=True)
    assert parse_settings(["--algo", "td3", "--scheduled-target-noise"]).algorithm().target_noise is None
    drqv2 = parse_settings(["--algo", "td3", "--online-target-actor", "--actor-loss", "min-noisy"]).algorithm()
    assert (drqv2.online_target_actor, drqv2.actor_loss) == (True, "min-noisy")
    assert parse_settings(["--algo", "td3"]).algorithm() == TD3Config()


def test_the_meter_averages_each_metric_over_the_batches_that_gave_it():
    meter = Meter()
    meter.add({"critic_loss": torch.tensor(1.0), "actor_loss": torch.tensor(4.0)}, 2, 64, 0.0)
    meter.add({"critic_loss": torch.tensor(3.0)}, 2, 64, 0.0)
    values = meter.report(meter.since + 1.0)
    assert (values["critic_loss"], values["actor_loss"]) == (2.0, 4.0)
