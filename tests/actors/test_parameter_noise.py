"""Parameter-space exploration: each world's perturbed policy, kept for its episode, with an adaptive std."""

import torch

from l2r.actors import parameter_noise
from l2r.actors.parameter_noise import ParameterNoise, perturbed_layers
from l2r.policy import DETERMINISTIC, build_policy, default_spec

OBS, ACT, WORLDS = 41, 18, 4


def policy(kind: str | None = None):
    spec = default_spec(OBS, ACT) | {"hidden": [32, 32], "layer_norm": True} | ({"kind": kind} if kind else {})
    torch.manual_seed(0)
    return build_policy(spec)


def test_the_linear_layers_are_perturbed_and_layer_norm_is_not():
    assert set(perturbed_layers(policy())) == {"trunk.0", "trunk.3", "head"}


def test_each_world_acts_with_its_own_perturbed_weights_as_the_plain_call_would():
    plain = policy()
    noise = ParameterNoise(0.2, WORLDS, seed=1)
    obs, draws = torch.randn(WORLDS, OBS), torch.randn(WORLDS, ACT)
    excitation, log_prob = noise.explore(plain, obs, draws)
    for world in range(WORLDS):  # world by world, a copy of the policy with that world's noise added
        copy = policy()
        with torch.no_grad():
            for name, layer in perturbed_layers(copy).items():
                layer.weight.add_(noise.noise[name][0][world])
                layer.bias.add_(noise.noise[name][1][world])
        expected = copy.explore(obs[world:world + 1], draws[world:world + 1])
        torch.testing.assert_close(excitation[world], expected[0][0])
        torch.testing.assert_close(log_prob[world], expected[1][0])
    unperturbed = plain.explore(obs, draws)[0]
    assert all(not torch.allclose(excitation[w], unperturbed[w]) for w in range(WORLDS))


def test_a_gaussian_policys_log_std_rows_stay_and_its_mean_rows_move():
    noise = ParameterNoise(0.2, WORLDS, seed=2)
    noise.explore(policy(), torch.randn(WORLDS, OBS), None)
    for head in noise.noise["head"]:
        assert head.shape[:2] == (WORLDS, 2 * ACT)
        assert (head[:, ACT:] == 0).all() and (head[:, :ACT] != 0).all()
    deterministic = ParameterNoise(0.2, WORLDS, seed=2)
    deterministic.explore(policy(DETERMINISTIC), torch.randn(WORLDS, OBS), None)
    assert all((head != 0).all() for head in deterministic.noise["head"])


def test_a_world_keeps_its_perturbation_until_its_episode_ends_and_a_new_policy_keeps_it_too():
    noise = ParameterNoise(0.2, WORLDS, seed=3)
    noise.explore(policy(), torch.randn(WORLDS, OBS), None)
    before = {name: w.clone() for name, (w, _) in noise.noise.items()}
    newer = policy()
    with torch.no_grad():
        for p in newer.parameters():
            p.add_(0.1)
    noise.explore(newer, torch.randn(WORLDS, OBS), None)
    assert all(torch.equal(before[name], w) for name, (w, _) in noise.noise.items())
    noise.reset(2)
    noise.explore(newer, torch.randn(WORLDS, OBS), None)
    changed = {w for w in range(WORLDS) if not torch.equal(before["trunk.0"][w], noise.noise["trunk.0"][0][w])}
    assert changed == {2}


def test_the_std_grows_while_the_actions_lie_closer_than_the_target_and_shrinks_while_further(monkeypatch):
    monkeypatch.setattr(parameter_noise, "ADAPT_EVERY", 1)
    obs = torch.randn(WORLDS, OBS)
    for distance, grows in ((10.0, True), (1e-6, False)):
        noise = ParameterNoise(distance, WORLDS, seed=4)
        for _ in range(5):
            noise.explore(policy(), obs, None)
        expected = parameter_noise.INITIAL_STD * parameter_noise.ADAPT_FACTOR ** (5 if grows else -5)
        assert abs(noise.std - expected) < 1e-12 and noise.last_distance > 0


def test_the_same_seed_draws_the_same_perturbations():
    first, second = ParameterNoise(0.2, WORLDS, seed=5), ParameterNoise(0.2, WORLDS, seed=5)
    obs = torch.randn(WORLDS, OBS)
    torch.testing.assert_close(first.explore(policy(), obs, None), second.explore(policy(), obs, None))

