"""A3C: the gradient an actor computes on a rollout against A2C's update on the same batch, the
learner's refusals (stale, wrong size), the gradient message on the wire, and --algo a3c."""

import copy
import dataclasses

import numpy as np
import pytest
import torch

from l2r.learner import a3c, ppo
from l2r.learner.__main__ import parse_settings
from l2r.learner.a2c import A2CConfig
from l2r.learner.a3c import A3CConfig
from l2r.policy import policy_state
from l2r.protocol import ExperienceChunk, Gradient, ProtocolError, Weights, decode, encode
from l2r.protocol.messages import PROTOCOL_VERSION

OBS, ACT = 3, 2
VERSION = 7


def rollout(seed: int = 0) -> ExperienceChunk:
    """Five steps of one environment: an episode that terminates at step 1, then one the chunk cuts."""
    rng = np.random.default_rng(seed)
    return ExperienceChunk(
        actor_id=0, env_id=0, epoch=1, seq=0, policy_version=VERSION,
        obs=rng.normal(size=(6, OBS)).astype(np.float32), actions=rng.random((5, ACT), dtype=np.float32),
        rewards=np.array([1.0, -2.0, 0.5, 3.0, 0.25], np.float32),
        terminated=np.array([False, True, False, False, False]), truncated=np.zeros(5, bool),
        final_obs=rng.normal(size=(1, OBS)).astype(np.float32))


def weights_of(state: ppo.TrainState, config: A3CConfig) -> Weights:
    """What an A3C learner publishes, through the wire format."""
    weights = Weights(state.version, policy_state(state.actor), dict(state.actor.spec), policy_state(state.value),
                      config.to_dict())
    return decode(encode(weights), Weights)


def learner(config: A3CConfig) -> ppo.TrainState:
    state = ppo.init_state(config, OBS, ACT, seed=1)
    state.version = VERSION
    # statistics of observations seen before, so that the rollout's merge shows
    state.actor.observation_filter.update(torch.randn(20, OBS) * 3 + 1)
    return state


def actor_gradient(state: ppo.TrainState, config: A3CConfig) -> Gradient:
    replica, replica_config = a3c.replica_of(weights_of(state, config))
    assert replica_config == config
    gradient, moments = a3c.gradient(replica, a3c.batch_from_chunk(rollout()), config)
    return decode(encode(Gradient(0, VERSION, 5, gradient, moments)), Gradient)


def a2c_twin(config: A3CConfig) -> A2CConfig:
    fields = {f.name: getattr(config, f.name) for f in dataclasses.fields(A2CConfig)}
    return A2CConfig(**fields)


@pytest.mark.parametrize("normalize_obs", [True, False])
def test_the_actors_gradient_is_a2cs_on_the_same_batch_and_applying_it_is_a2cs_step(normalize_obs):
    # Unclipped, so that A2C's gradients stay as its loss gave them, to compare.
    config = A3CConfig(hidden=(8, 8), normalize_obs=normalize_obs, max_grad_norm=1e9, entropy_coef=0.01)
    state = learner(config)
    a2c_state = copy.deepcopy(state)

    message = actor_gradient(state, config)
    # A2C's update on the same rollout as a queue batch, acted by the learner's own policy.
    batch = a3c.batch_from_chunk(rollout())
    with torch.no_grad():
        batch.behaviour_log_prob = a2c_state.actor.evaluate(batch.obs, batch.action)[0]
    ppo.update(a2c_state, batch, a2c_twin(config))
    a2c_gradient = torch.cat([p.grad.reshape(-1) for p in a2c_state.parameters()]).numpy()
    assert np.abs(a2c_gradient).max() > 1e-3
    np.testing.assert_allclose(message.gradient, a2c_gradient, rtol=1e-4, atol=1e-6)

    metrics = a3c.apply(state, message, config)
    for mine, theirs in zip(state.parameters(), a2c_state.parameters()):
        torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-6)
    for name, buffer in a2c_state.actor.observation_filter.named_buffers():
        torch.testing.assert_close(getattr(state.actor.observation_filter, name), buffer)
    assert (message.obs_moments is None) != normalize_obs
    assert state.updates == 1 and float(metrics["staleness"]) == 0.0


def test_the_gradient_is_the_hand_written_a2c_loss_s():
    # Lambda 1, gamma .99: the n-step returns to the end of each piece, by hand.
    config = A3CConfig(hidden=(8, 8), max_grad_norm=1e9)
    state = learner(config)
    message = actor_gradient(state, config)
    chunk = rollout()
    obs, next_obs = torch.as_tensor(chunk.obs[:-1]), torch.as_tensor(chunk.next_obs())
    action = torch.as_tensor(chunk.actions) * 2 - 1
    r, g = torch.as_tensor(chunk.rewards), config.gamma
    with torch.no_grad():
        v_last = state.value(state.actor.observation_filter(next_obs[4]))
        g1 = r[1]  # terminates
        g4 = r[4] + g * v_last
        g3 = r[3] + g * g4
        g2 = r[2] + g * g3
        returns = torch.stack([r[0] + g * g1, g1, g2, g3, g4])
    values = state.value(state.actor.observation_filter(obs))
    log_prob, _ = state.actor.evaluate(obs, action)
    loss = -((returns - values.detach()) * log_prob).mean() + 0.5 * (values - returns).pow(2).mean()
    expected = torch.cat([x.reshape(-1) for x in torch.autograd.grad(loss, state.parameters())]).numpy()
    np.testing.assert_allclose(message.gradient, expected, rtol=1e-4, atol=1e-6)


def test_the_learner_refuses_stale_and_ill_fitting_gradients_and_stays_as_it_was():
    config = A3CConfig(hidden=(8, 8), normalize_obs=True, max_gradient_staleness=2)
    state = learner(config)
    good = actor_gradient(state, config)
    before = copy.deepcopy(state.state_dict())
    refused = {
        "stale": dataclasses.replace(good, policy_version=VERSION - 3),
        "ahead": dataclasses.replace(good, policy_version=VERSION + 1),
        "wrong size": dataclasses.replace(good, gradient=good.gradient[:-1]),
        "no moments": dataclasses.replace(good, obs_moments=None),
        "moments of another width": dataclasses.replace(good, obs_moments=good.obs_moments[:-2]),
    }
    reasons = {}
    for name, message in refused.items():
        with pytest.raises(ProtocolError) as e:
            a3c.apply(state, message, config)
        reasons[name] = e.value.reason
    assert reasons == {"stale": "stale", "ahead": "ahead", "wrong size": "wrong_size", "no moments": "wrong_size",
                       "moments of another width": "wrong_size"}
    after = state.state_dict()
    for net in ("actor", "value"):
        for key, tensor in before[net].items():
            torch.testing.assert_close(after[net][key], tensor)
    assert state.updates == 0
    a3c.apply(state, dataclasses.replace(good, policy_version=VERSION - 2), config)  # as stale as allowed
    assert state.updates == 1


def raw_gradient(**changes) -> bytes:
    import msgpack
    message = {"v": 1, "kind": "gradient", "actor_id": 0, "policy_version": 3, "env_steps": 5,
               "gradient": {"dtype": "<f4", "shape": [3], "data": np.array([1.0, 2.0, 3.0], np.float32).tobytes()}}
    return msgpack.packb(message | changes)


def test_a_gradient_round_trips_and_decode_refuses_nan_wrong_dtypes_and_other_protocol_versions():
    message = Gradient(4, 9, 5, np.arange(6, dtype=np.float32), np.array([2.0, 1.0, 3.0]))
    back = decode(encode(message), Gradient)
    assert (back.actor_id, back.policy_version, back.env_steps) == (4, 9, 5)
    np.testing.assert_array_equal(back.gradient, message.gradient)
    np.testing.assert_array_equal(back.obs_moments, message.obs_moments)
    assert decode(raw_gradient(), Gradient).gradient.tolist() == [1.0, 2.0, 3.0]

    nan = {"dtype": "<f4", "shape": [2], "data": np.array([1.0, np.nan], np.float32).tobytes()}
    float64 = {"dtype": "<f8", "shape": [1], "data": np.array([1.0]).tobytes()}
    cases = {"not_finite": raw_gradient(gradient=nan), "wrong_dtype": raw_gradient(gradient=float64),
             "version": raw_gradient(v=PROTOCOL_VERSION + 1), "out_of_range": raw_gradient(policy_version=-2),
             "shape_mismatch": raw_gradient(obs_moments={"dtype": "<f8", "shape": [2],
                                                         "data": np.array([1.0, 1.0]).tobytes()})}
    for reason, payload in cases.items():
        with pytest.raises(ProtocolError) as e:
            decode(payload, Gradient)
        assert e.value.reason == reason


def test_weights_without_a3cs_value_network_give_no_replica():
    config = A3CConfig(hidden=(8, 8))
    state = learner(config)
    weights = dataclasses.replace(weights_of(state, config), value_params=None, training=None)
    with pytest.raises(ValueError, match="not an A3C learner's"):
        a3c.replica_of(weights)


def test_algo_a3c_is_a2cs_settings_with_the_staleness_bound():
    assert parse_settings(["--algo", "a3c"]).algorithm() == A3CConfig()
    given = parse_settings(["--algo", "a3c", "--max-gradient-staleness", "1", "--lr", "1e-3"]).algorithm()
    assert (given.max_gradient_staleness, given.lr, given.batch_size, given.optimizer) == (1, 1e-3, 5, "rmsprop")
