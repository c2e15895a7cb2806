"""The policy network shared by the learner and the actors.

Two kinds over the 18 muscle excitations, one network shape (observation filter, hidden layers,
linear head): "gaussian", a tanh-squashed Gaussian (SAC, PPO), and "deterministic", tanh(mu(s))
explored with Gaussian noise (TD3). The network works in tanh space (-1, 1); `act` maps its
output to excitations in [0, 1], the environment's action space. The learner maps stored
excitations back with `to_tanh_space` before training on them.

The architecture travels as a small spec dict in the weights message, so an actor can
rebuild exactly the network the learner trains:

    {"obs_dim": 41, "act_dim": 18, "hidden": [512, 512, 512], "activation": "elu",
     "layer_norm": true, "relative_x": false, "normalize_obs": false, "kind": "gaussian"}

A spec without "kind" (from before the deterministic kind) is a Gaussian one. A vector policy
with "frame_stack": k takes the last k observations, oldest first, concatenated (an observation
history; an actor keeps them, the replay stacks them when it samples). A policy of image
observations has no "obs_dim"; its spec says what it takes instead (l2r.encoders):

    {"observation": [{"name": "pixels", "dtype": "uint8", "shape": [3, 84, 84]}], "frame_stack": 3,
     "encoder": {"channels": 32, "features": 50}, "act_dim": 6, ...}

A third kind, "residual", is the deterministic one whose action is a change to the last: its spec's
"residual": i is the index in the float32 vector (or the "state" field) where the observation
holds the action of the last step, in the policy's (-1, 1) space, and its action is
tanh(atanh(that action) + head), so that a head of 0 repeats it (the photo tuner refining its last
query's parameters, l2r.photo.env). A peer that knows no such kind refuses its weights.

Its "encoder" has a "kind" where it is not DrQ-v2's: {"kind": "dual", "channels": 32, "features": 50}
(RLPixTuner's dual-path encoder); without one, it is DrQ-v2's, as every spec from before kinds.

The network's first layer sees the observation through an `ObservationFilter` (x coordinates
measured from the pelvis, running standardisation), part of the network's state: the filter's
statistics travel with the weights and the checkpoint, so an actor and `l2r eval` feed the
network exactly what the learner does.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from functools import partial

import numpy as np
import torch
from torch import nn

from l2r import encoders
from l2r.protocol.errors import ProtocolError
from l2r.protocol.limits import MAX_FRAME_STACK
from l2r.protocol.observations import VECTOR_FIELD, ObservationSpec
from l2r.sim import layout

LOG_STD_MIN, LOG_STD_MAX = -5.0, 2.0
# Stored actions are float32 excitations, so +-1 comes back exactly; the log-probability of a
# given action is taken at most this close to the edge, by actors and learner alike.
EDGE = 1e-6
# In place: every activation follows a Linear or a LayerNorm, whose backward passes do not read
# their output, so it may be overwritten: one tensor fewer per layer, and ELU's backward then
# works from its result, the faster of its two kernels.
ACTIVATIONS = {"elu": partial(nn.ELU, inplace=True), "relu": partial(nn.ReLU, inplace=True), "tanh": nn.Tanh}
SPEC_KEYS = ("obs_dim", "act_dim", "hidden", "activation", "layer_norm")
# Observation options; a spec from before they existed means "off".
FILTER_KEYS = ("relative_x", "normalize_obs")
GAUSSIAN, DETERMINISTIC, RESIDUAL = "gaussian", "deterministic", "residual"
# A residual policy's last action is taken at most this close to the bounds, where atanh would
# be infinite: a change of the head can still move it back.
RESIDUAL_EDGE = 1e-3


def default_spec(obs_dim: int = 41, act_dim: int = 18) -> dict:
    """The reference architecture: three hidden layers of 512, ELU, LayerNorm, raw observations."""
    return {"obs_dim": obs_dim, "act_dim": act_dim, "hidden": [512, 512, 512],
            "activation": "elu", "layer_norm": True, "relative_x": False, "normalize_obs": False,
            "kind": GAUSSIAN}


def check_spec(spec: Mapping) -> dict:
    """Return a clean copy of an architecture spec, or raise ValueError saying what is wrong.

    A spec of the float32 vector `state` comes back in the form it has always had ("obs_dim", no
    "observation"), with "frame_stack" where the policy takes the last k observations (k > 1);
    any other observation comes with "observation" (its wire form), "frame_stack" and "encoder"
    (`check_encoder`)."""
    if not isinstance(spec, Mapping):
        raise ValueError(f"policy spec must be a mapping, got {type(spec).__name__}")
    required = [k for k in SPEC_KEYS if k != "obs_dim" or "observation" not in spec]
    missing = [k for k in required if k not in spec]
    if missing:
        raise ValueError(f"policy spec lacks {missing}")
    hidden = spec["hidden"]
    if (not isinstance(hidden, Sequence) or not hidden
            or not all(isinstance(h, int) and 0 < h <= 65536 for h in hidden)):
        raise ValueError(f"policy spec 'hidden' must be a non-empty list of widths, got {hidden!r}")
    for key in ("obs_dim", "act_dim"):
        if key in required and (not isinstance(spec[key], int) or not 0 < spec[key] <= 65536):
            raise ValueError(f"policy spec {key!r} must be a positive int, got {spec[key]!r}")
    if spec["activation"] not in ACTIVATIONS:
        raise ValueError(f"policy spec 'activation' must be one of {sorted(ACTIVATIONS)}, "
                         f"got {spec['activation']!r}")
    options = {key: bool(spec.get(key, False)) for key in FILTER_KEYS}
    kind = spec.get("kind", GAUSSIAN)
    if not isinstance(kind, str) or kind not in POLICIES:
        raise ValueError(f"policy spec 'kind' must be one of {sorted(POLICIES)}, got {kind!r}")
    common = {"act_dim": spec["act_dim"], "hidden": list(hidden), "activation": spec["activation"],
              "layer_norm": bool(spec["layer_norm"]), **options, "kind": kind}
    observation, frame_stack = _observation_of(spec)
    common |= _residual_of(spec, observation, frame_stack, kind)
    if observation.vector_width is not None:
        if options["relative_x"] and observation.vector_width != layout.OBS_SIZE:
            raise ValueError(f"policy spec 'relative_x' needs the {layout.OBS_SIZE} Learning to Run observations, "
                             f"got obs_dim {observation.vector_width}")
        history = {"frame_stack": frame_stack} if frame_stack > 1 else {}
        return {"obs_dim": observation.vector_width, **history, **common}
    if options["relative_x"] or options["normalize_obs"]:
        raise ValueError(f"policy spec 'relative_x' and 'normalize_obs' are for the float32 vector alone, not "
                         f"observation {observation} stacked {frame_stack}")
    encoder = check_encoder(spec.get("encoder", {}))
    encoders.check_observation(observation, encoder.get("kind", encoders.DRQ))
    return {"observation": observation.to_wire(), "frame_stack": frame_stack, "encoder": encoder, **common}


def _observation_of(spec: Mapping) -> tuple[ObservationSpec, int]:
    """The observation and frame stack a spec's networks take; ValueError when they cannot."""
    try:
        observation = ObservationSpec.from_policy_spec(spec)
    except ProtocolError as e:
        raise ValueError(f"policy spec: {e}") from None
    if "observation" in spec and "obs_dim" in spec and spec["obs_dim"] != observation.vector_width:
        raise ValueError(f"policy spec 'obs_dim' {spec['obs_dim']!r} is not the width of observation {observation}")
    frame_stack = spec.get("frame_stack", 1)
    if type(frame_stack) is not int or not 1 <= frame_stack <= MAX_FRAME_STACK:
        raise ValueError(f"policy spec 'frame_stack' must be an int from 1 to {MAX_FRAME_STACK}, got {frame_stack!r}")
    return observation, frame_stack


def _residual_of(spec: Mapping, observation: ObservationSpec, frame_stack: int, kind: str) -> dict:
    """{"residual": index} of a residual policy's spec (see the module docstring), else {}."""
    index = spec.get("residual")
    if kind != RESIDUAL:
        if index is not None:
            raise ValueError(f"policy spec 'residual' is for the residual kind, not {kind}")
        return {}
    state = observation.fields.get(VECTOR_FIELD)
    width = None if state is None or state.dtype != np.float32 else state.shape[0]
    if frame_stack != 1 or width is None:
        raise ValueError(f"a residual policy reads its last action from one float32 state, not {observation} "
                         f"stacked {frame_stack}")
    if type(index) is not int or not 0 <= index <= width - spec["act_dim"]:
        raise ValueError(f"policy spec 'residual' must be an index from 0 to {width - spec['act_dim']} of the "
                         f"{width} state values, got {index!r}")
    return {"residual": index}


def check_encoder(entry: Mapping) -> dict:
    """The image encoder of a spec ("encoder"), each size at DrQ-v2's value when not given: "kind"
    (`encoders.IMAGE_VIEWS`; left out for DrQ-v2's, so its specs stay as they always were),
    "channels" of every convolution, "features" out of each network's projection."""
    if not isinstance(entry, Mapping) or set(entry) - {"kind", "channels", "features"}:
        raise ValueError(f"policy spec 'encoder' must be a map of kind, channels and features, got {entry!r:.80}")
    kind = entry.get("kind", encoders.DRQ)
    if not isinstance(kind, str) or kind not in encoders.IMAGE_VIEWS:
        raise ValueError(f"policy spec encoder 'kind' must be one of {sorted(encoders.IMAGE_VIEWS)}, got {kind!r:.80}")
    sizes = {"channels": entry.get("channels", encoders.CHANNELS), "features": entry.get("features", encoders.FEATURES)}
    for key, value in sizes.items():
        if type(value) is not int or not 0 < value <= 4096:
            raise ValueError(f"policy spec encoder {key!r} must be an int from 1 to 4096, got {value!r}")
    return sizes if kind == encoders.DRQ else {"kind": kind, **sizes}


def mlp_trunk(in_dim: int, hidden: Sequence[int], activation: str, layer_norm: bool) -> nn.Sequential:
    """Hidden layers: Linear, then LayerNorm (optional), then the activation."""
    layers: list[nn.Module] = []
    for width in hidden:
        layers.append(nn.Linear(in_dim, width))
        if layer_norm:
            layers.append(nn.LayerNorm(width))
        layers.append(ACTIVATIONS[activation]())
        in_dim = width
    return nn.Sequential(*layers)


class ObservationFilter(nn.Module):
    """What the networks see of an observation.

    relative_x: world x coordinates (pelvis, centre of mass, tracked bodies) become distances
        from the pelvis, so the input does not drift as the runner gets further.
    normalize: each value minus its running mean, over its running standard deviation, clipped
        to +-CLIP. `update` adds a batch to the statistics (the learner's job). The deviation has
        a floor of MIN_STD: a value that has never varied (the psoas strengths and obstacle at
        difficulty 0) reads 0 until it does, then hits the clip.
    frames: observations of `obs_dim` values concatenated in each input (an observation
        history); each is filtered as one alone would be, with the same statistics.
    """

    CLIP = 5.0
    MIN_STD = 1e-2

    def __init__(self, obs_dim: int, relative_x: bool, normalize: bool, frames: int = 1):
        super().__init__()
        self.relative_x, self.normalize, self.frames = relative_x, normalize, frames
        if relative_x:
            self.register_buffer("world_x", torch.tensor((layout.PELVIS_X, *layout.WORLD_X)), persistent=False)
        if normalize:
            self.register_buffer("mean", torch.zeros(obs_dim, dtype=torch.float64))
            self.register_buffer("var", torch.ones(obs_dim, dtype=torch.float64))
            self.register_buffer("count", torch.zeros((), dtype=torch.float64))

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if not (self.relative_x or self.normalize):
            return obs
        shape = obs.shape
        obs = self._relative(self._per_frame(obs))
        if self.normalize:
            std = self.var.sqrt().clamp(min=self.MIN_STD)
            obs = ((obs - self.mean) / std).to(obs.dtype).clamp(-self.CLIP, self.CLIP)
        return obs.reshape(shape)

    def _per_frame(self, obs: torch.Tensor) -> torch.Tensor:
        """(..., frames * obs_dim) as (..., frames, obs_dim): one row per observation."""
        return obs if self.frames == 1 else obs.unflatten(-1, (self.frames, -1))

    def _relative(self, obs: torch.Tensor) -> torch.Tensor:
        if not self.relative_x:
            return obs
        pelvis_x = obs[..., layout.PELVIS_X:layout.PELVIS_X + 1]
        return obs.index_add(-1, self.world_x, -pelvis_x.expand(*obs.shape[:-1], len(self.world_x)))

    @torch.no_grad()
    def update(self, obs: torch.Tensor, reduce=None) -> None:
        """Merge a batch (n, obs_dim) into the running statistics (Chan et al.'s parallel rule).

        `reduce`, if given, sums a tensor over data-parallel ranks in place, so every rank merges
        the same global batch and the statistics stay identical.
        """
        if not self.normalize:
            return
        moments = self.moments(obs)
        if reduce is not None:
            reduce(moments)
        self.merge(moments)

    @torch.no_grad()
    def moments(self, obs: torch.Tensor) -> torch.Tensor:
        """What `update` merges of a batch (n, frames * obs_dim): float64 [number of observations,
        sum of them, sum of their squares]."""
        x = self._relative(self._per_frame(obs)).double().flatten(0, -2)
        count = torch.full((1,), len(x), dtype=x.dtype, device=x.device)  # a fill: no copy that waits for a GPU
        return torch.cat([count, x.sum(0), x.pow(2).sum(0)])

    @torch.no_grad()
    def merge(self, moments: torch.Tensor) -> None:
        """Merge a batch's `moments` into the running statistics."""
        width = len(self.mean)
        n, total, squares = moments[0], moments[1:1 + width], moments[1 + width:]
        batch_mean = total / n
        batch_var = (squares / n - batch_mean.pow(2)).clamp(min=0.0)
        count = self.count + n
        delta = batch_mean - self.mean
        self.var.copy_((self.var * self.count + batch_var * n + delta.pow(2) * self.count * n / count) / count)
        self.mean.add_(delta * n / count)
        self.count.copy_(count)


class PolicyNetwork(nn.Module):
    """What every policy kind is: the spec, what it sees of an observation, the hidden layers and
    a linear head of `outputs` values per action dimension.

    What it sees: the float32 vector through the `ObservationFilter`; an observation with image
    fields through `encoder` (a `PixelEncoder`, which a learner's critics share) and the policy's
    own `projection` (see l2r.encoders). The two steps are apart (`embed`, then `head_output_of`)
    so a learner can embed a batch once for actor and critics. The vector's networks have neither
    module: their state_dict keys are those they always had."""

    KIND = ""
    """The spec's "kind" of the subclass."""

    def __init__(self, spec: Mapping, outputs: int):
        super().__init__()
        self.spec = check_spec(spec)
        if self.spec["kind"] != self.KIND:
            raise ValueError(f"a {self.KIND} policy cannot be built from a {self.spec['kind']} spec")
        self.observation, self.frame_stack = _observation_of(self.spec)
        if "encoder" in self.spec:
            self.image_fields = encoders.image_fields(self.observation)
            encoder = self.spec["encoder"]
            self.encoder = encoders.PixelEncoder(self.observation, self.frame_stack, encoder["channels"],
                                                 encoder.get("kind", encoders.DRQ))
            self.projection = encoders.Projection(self.encoder.conv_dim, self.encoder.vector_dim, encoder["features"])
            features = self.projection.out_dim
        else:
            self.image_fields, self.encoder, self.projection = [], None, None
            self.observation_filter = ObservationFilter(self.spec["obs_dim"], self.spec["relative_x"],
                                                        self.spec["normalize_obs"], self.frame_stack)
            features = self.spec["obs_dim"] * self.frame_stack
        self.trunk = mlp_trunk(features, self.spec["hidden"], self.spec["activation"], self.spec["layer_norm"])
        self.head = nn.Linear(self.spec["hidden"][-1], outputs * self.spec["act_dim"])

    def embed(self, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        """What the networks see of a batch of observations: the filtered vector, or the
        encoder's embedding of the fields (images stacked, uint8)."""
        return self.observation_filter(obs) if self.encoder is None else self.encoder(obs)

    def head_output(self, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        return self.head_output_of(self.embed(obs))

    def head_output_of(self, embedding: torch.Tensor) -> torch.Tensor:
        features = self.trunk(embedding if self.projection is None else self.projection(embedding))
        # The head stays in float32 under mixed precision: actions, means and log-stds need the bits.
        with torch.autocast(embedding.device.type, enabled=False):
            return self.head(features.float())

    def observation_tensors(self, obs: np.ndarray | Mapping[str, np.ndarray],
                            device: torch.device) -> torch.Tensor | dict[str, torch.Tensor]:
        """A batch of observations as the network takes them, on `device`: a float32 matrix of the
        vector (given as an array, or as the field "state"), or the map of stacked fields, uint8
        images as they are (see `act`)."""
        if self.encoder is None:
            vector = np.asarray(obs[VECTOR_FIELD] if isinstance(obs, Mapping) else obs, dtype=np.float32)
            width = self.spec["obs_dim"] * self.frame_stack
            if vector.ndim != 2 or vector.shape[1] != width:
                raise ValueError(f"observations of shape {list(vector.shape)}, this policy takes [n, {width}]"
                                 + (f" ({self.frame_stack} observations of {self.spec['obs_dim']} stacked)"
                                    if self.frame_stack > 1 else ""))
            return torch.as_tensor(vector, device=device)
        if not isinstance(obs, Mapping) or set(obs) != set(self.observation.fields):
            raise ValueError(f"this policy takes observations of fields {self.observation}, stacked "
                             f"{self.frame_stack}, as a map of arrays; got "
                             f"{sorted(obs) if isinstance(obs, Mapping) else type(obs).__name__}")
        tensors = {}
        for name, field in self.observation.fields.items():
            stacked = (self.frame_stack * field.shape[0], *field.shape[1:])
            array = np.asarray(obs[name], dtype=field.dtype)
            if array.shape[1:] != stacked:
                raise ValueError(f"observation field {name!r}: shape {list(array.shape)}, this policy takes "
                                 f"[n, {', '.join(map(str, stacked))}] ({self.frame_stack} frames of {field} stacked)")
            tensors[name] = torch.as_tensor(array, device=device)
        return tensors

    @torch.no_grad()
    def act(self, obs_batch: np.ndarray | Mapping[str, np.ndarray], deterministic: bool = False) -> np.ndarray:
        """Excitations in [0, 1] for a batch of observations, shape (n, obs_dim) -> (n, act_dim)."""
        return act(self, obs_batch, deterministic)


class Policy(PolicyNetwork):
    """Tanh-Gaussian policy: observation -> mean and log-std of a pre-tanh Gaussian."""

    KIND = GAUSSIAN

    def __init__(self, spec: Mapping):
        super().__init__(spec, outputs=2)

    def forward(self, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        return self.distribution_of(self.embed(obs))

    def distribution_of(self, embedding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and log-std of the pre-tanh Gaussian of an observation embedded (`embed`)."""
        mean, log_std = self.head_output_of(embedding).chunk(2, dim=-1)
        # Squash log-std smoothly into its bounds so gradients never vanish at a hard clip.
        log_std = LOG_STD_MIN + 0.5 * (LOG_STD_MAX - LOG_STD_MIN) * (torch.tanh(log_std) + 1)
        return mean, log_std

    def sample_of(self, embedding: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """A reparameterised action in (-1, 1) and its log-probability (summed over dims), of an
        observation embedded (`embed`): a learner embeds a batch once for all its networks."""
        mean, log_std = self.distribution_of(embedding)
        std = log_std.exp()
        noise = torch.randn_like(mean)
        pre_tanh = mean + std * noise
        action = torch.tanh(pre_tanh)
        return action, _log_density(noise, pre_tanh, log_std)

    def evaluate(self, obs: torch.Tensor, action: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """log pi(action | obs) of given actions in (-1, 1) (summed over dims), and the entropy
        of the Gaussian before the tanh (the squashed one has no closed form)."""
        mean, log_std = self(obs)
        entropy = (log_std + 0.5 * math.log(2 * math.pi * math.e)).sum(-1)
        return tanh_gaussian_log_prob(mean, log_std, action), entropy

    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        """The deterministic action in (-1, 1): the tanh of the mean."""
        return torch.tanh(self(obs)[0])

    def explore(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Sampled excitations in [0, 1] and the log-probability of each, taken of the excitation
        as sent (float32, mapped back with `to_tanh_space`), so the learner, computing it from
        the stored action, gets the same number. `noise`: the standard normal draws to sample
        with (`l2r.actors.noise`, correlated in time); None draws them here."""
        mean, log_std = self(obs)
        noise = torch.randn_like(mean) if noise is None else noise
        excitation = to_excitation(torch.tanh(mean + log_std.exp() * noise))
        return excitation, tanh_gaussian_log_prob(mean, log_std, to_tanh_space(excitation))


class DeterministicPolicy(PolicyNetwork):
    """Deterministic policy: observation -> tanh(mu(s)) in (-1, 1).

    It explores by adding N(0, exploration_std) to each action value and clipping the sum to the
    bounds [-1, 1]; the noise itself is not clipped (as DrQ-v2 and Stable-Baselines3 explore).
    `exploration_std` is a buffer, so the std the learner schedules travels with the weights and
    the checkpoint."""

    KIND = DETERMINISTIC

    def __init__(self, spec: Mapping):
        super().__init__(spec, outputs=1)
        self.register_buffer("exploration_std", torch.zeros(()))

    def forward(self, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        return self.action_of(self.embed(obs), obs)

    def action_of(self, embedding: torch.Tensor, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        """The action of an observation `obs` embedded (`embed`; the residual kind reads `obs` too)."""
        return torch.tanh(self.head_output_of(embedding))

    def mean_action(self, obs: torch.Tensor) -> torch.Tensor:
        return self(obs)

    def explore(self, obs: torch.Tensor, noise: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Explored excitations in [0, 1], and 0 for each log-probability: TD3 reads none, and an
        action clipped at a bound has no density to give. `noise`: standard normal draws, as the
        Gaussian policy's."""
        action = self(obs)
        noise = torch.randn_like(action) if noise is None else noise
        action = (action + self.exploration_std * noise).clamp(-1.0, 1.0)
        return to_excitation(action), action.new_zeros(len(action))


class ResidualPolicy(DeterministicPolicy):
    """Deterministic policy of changes: tanh(atanh(last action) + mu(s)), the last action read from
    the observation's state at the spec's "residual" index; explored as its parent."""

    KIND = RESIDUAL

    def action_of(self, embedding: torch.Tensor, obs: torch.Tensor | Mapping[str, torch.Tensor]) -> torch.Tensor:
        state = obs[VECTOR_FIELD] if isinstance(obs, Mapping) else obs
        index = self.spec["residual"]
        last = state[..., index:index + self.spec["act_dim"]].clamp(-1.0 + RESIDUAL_EDGE, 1.0 - RESIDUAL_EDGE)
        return torch.tanh(torch.atanh(last) + self.head_output_of(embedding))


def tanh_gaussian_log_prob(mean: torch.Tensor, log_std: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
    """log-density of actions in (-1, 1) under the tanh-squashed Gaussian (mean, log_std)."""
    pre_tanh = torch.atanh(action.clamp(-1.0 + EDGE, 1.0 - EDGE))
    return _log_density((pre_tanh - mean) / log_std.exp(), pre_tanh, log_std)


def _log_density(noise: torch.Tensor, pre_tanh: torch.Tensor, log_std: torch.Tensor) -> torch.Tensor:
    # log N(pre_tanh; mean, std) minus the log-determinant of tanh, in a stable form:
    # log(1 - tanh(x)^2) = 2 * (log 2 - x - softplus(-2x)).
    gauss = -0.5 * noise.pow(2) - log_std - 0.5 * math.log(2 * math.pi)
    squash = 2.0 * (math.log(2.0) - pre_tanh - nn.functional.softplus(-2.0 * pre_tanh))
    return (gauss - squash).sum(-1)


def build_policy(spec: Mapping) -> PolicyNetwork:
    """A freshly initialised policy of the spec's kind (see module docstring)."""
    return POLICIES[check_spec(spec)["kind"]](spec)


@torch.no_grad()
def act(policy: PolicyNetwork, obs_batch: np.ndarray | Mapping[str, np.ndarray],
        deterministic: bool = False) -> np.ndarray:
    """Excitations in [0, 1], float32, for a batch of observations (runs on the policy's device).

    The observations: a float32 array (n, width) of the vector, or a map of each field stacked
    `frame_stack` deep along its first dimension, oldest first: an image field uint8
    (n, k*C, H, W), a float32 field (n, k*width) (`ObservationSpec.from_policy_spec(policy.spec)`
    and `policy.spec.get("frame_stack", 1)` say which)."""
    obs = policy.observation_tensors(obs_batch, next(policy.parameters()).device)
    excitation = to_excitation(policy.mean_action(obs)) if deterministic else policy.explore(obs)[0]
    return excitation.cpu().numpy()


@torch.no_grad()
def act_with_log_prob(policy: PolicyNetwork, obs_batch: np.ndarray | Mapping[str, np.ndarray],
                      noise: np.ndarray | None = None, explore=None) -> tuple[np.ndarray, np.ndarray]:
    """Exploring excitations in [0, 1] and the log-probability of each, float32 (see each kind's
    `explore`; observations as `act` takes them; `noise`, [n, act_dim] standard normal draws, or
    None for the policy's own; `explore`, what explores in place of `policy.explore`, called
    alike, e.g. with perturbed weights: l2r.actors.parameter_noise)."""
    device = next(policy.parameters()).device
    draws = None if noise is None else torch.as_tensor(noise, dtype=torch.float32, device=device)
    excitation, log_prob = (explore or policy.explore)(policy.observation_tensors(obs_batch, device), draws)
    return excitation.cpu().numpy(), log_prob.cpu().numpy()


def uniform_log_prob(act_dim: int) -> float:
    """log-density of uniform random excitations (the actors' warm-up) in the policy's (-1, 1) space."""
    return -act_dim * math.log(2.0)


def to_excitation(tanh_action: torch.Tensor) -> torch.Tensor:
    """Map the policy's (-1, 1) output to the environment's [0, 1] excitations."""
    return (tanh_action + 1.0) * 0.5


def to_tanh_space(excitation: torch.Tensor) -> torch.Tensor:
    """Map stored [0, 1] excitations back to the policy's (-1, 1) space."""
    return excitation * 2.0 - 1.0


def policy_state(policy: PolicyNetwork) -> dict[str, np.ndarray]:
    """The policy's parameters as float32 numpy arrays, keyed by parameter name."""
    return {name: t.detach().to("cpu", torch.float32).numpy().copy()
            for name, t in policy.state_dict().items()}


def load_policy_state(policy: PolicyNetwork, arrays: Mapping[str, np.ndarray]) -> None:
    """Copy arrays from `policy_state` into the policy; ValueError on missing keys or bad shapes."""
    own = policy.state_dict()
    missing = sorted(set(own) - set(arrays))
    unexpected = sorted(set(arrays) - set(own))
    if missing or unexpected:
        raise ValueError(f"policy weights do not match the network: missing {missing}, "
                         f"unexpected {unexpected}")
    for name, target in own.items():
        array = np.asarray(arrays[name])
        if tuple(array.shape) != tuple(target.shape):
            raise ValueError(f"policy weight {name!r} has shape {tuple(array.shape)}, "
                             f"the network expects {tuple(target.shape)}")
        if not np.isfinite(array).all():
            raise ValueError(f"policy weight {name!r} holds NaN or infinite values")
    with torch.no_grad():
        for name, target in own.items():
            target.copy_(torch.from_numpy(np.array(arrays[name], dtype=np.float32)))


# The network of each spec "kind".
POLICIES = {GAUSSIAN: Policy, DETERMINISTIC: DeterministicPolicy, RESIDUAL: ResidualPolicy}
