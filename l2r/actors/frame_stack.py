"""The last k observations of each environment, stacked as a policy takes them.

An actor sends one frame per step and the replay builds stacks of k when it samples
(docs/observations.md); acting needs the same stacks at once, so the actor keeps the last k
observations of every environment here. An episode's first observation fills all k places:
the padding the replay applies where an episode begins (the oldest frame found, repeated), so
a policy acts on the stacks the learner trains it on.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from l2r.protocol import ProtocolError
from l2r.protocol.limits import MAX_FRAME_STACK
from l2r.protocol.observations import VECTOR_FIELD, ObservationSpec


def frame_stack_of(policy_spec: Mapping) -> int:
    """How many observations a policy of ``policy_spec`` takes stacked: its "frame_stack", 1 in
    specs without one; ProtocolError (``bad_spec``) unless 1 to MAX_FRAME_STACK, the stacks a
    replay shard builds."""
    depth = policy_spec.get("frame_stack", 1)
    if type(depth) is not int or not 1 <= depth <= MAX_FRAME_STACK:
        raise ProtocolError(f"policy spec frame_stack {depth!r:.40} is not a whole number from 1 to {MAX_FRAME_STACK}",
                            "bad_spec")
    return depth


class FrameStack:
    """Per field, ``[num_envs, depth, *shape]`` in the field's own dtype, oldest first."""

    def __init__(self, spec: ObservationSpec, depth: int, num_envs: int):
        if not isinstance(depth, int) or depth < 1:
            raise ValueError(f"a frame stack holds at least one observation, got depth {depth!r}")
        self.spec, self.depth, self.num_envs = spec, depth, num_envs
        self._frames = {name: np.zeros((num_envs, depth, *field.shape), field.dtype)
                        for name, field in spec.fields.items()}

    def reset(self, env: int, observation: Mapping[str, np.ndarray]) -> None:
        """The first observation of an episode of env ``env``: it fills every place of the stack."""
        for name, frames in self._frames.items():
            frames[env] = observation[name]

    def push(self, env: int, observation: Mapping[str, np.ndarray]) -> None:
        """The next observation of env ``env``: the oldest one drops out."""
        for name, frames in self._frames.items():
            frames[env, :-1] = frames[env, 1:]
            frames[env, -1] = observation[name]

    def stacked(self, envs: Sequence[int] | None = None) -> np.ndarray | dict[str, np.ndarray]:
        """The stacks of ``envs`` (default: all), as `l2r.policy.act` takes them, copies: the float32
        vector ``[n, width]`` itself when the observation is that vector and the depth 1 (the
        input of vector policies from before stacks); otherwise field -> the k observations
        concatenated along their first axis, oldest first: ``[n, k*C, H, W]`` for an image,
        ``[n, k*width]`` for a vector."""
        rows = np.arange(self.num_envs) if envs is None else np.asarray(envs, np.intp)  # indexing copies
        if self.depth == 1 and self.spec.vector_width is not None:
            return self._frames[VECTOR_FIELD][rows, 0]
        out = {}
        for name, frames in self._frames.items():
            chosen = frames[rows]
            out[name] = chosen.reshape(len(chosen), self.depth * frames.shape[2], *frames.shape[3:])
        return out

    def with_depth(self, depth: int) -> FrameStack:
        """A stack of another depth holding the newest observations of this one; where it is
        deeper, the oldest one kept fills the places before it, as at a reset."""
        other = FrameStack(self.spec, depth, self.num_envs)
        kept = min(depth, self.depth)
        for name, frames in self._frames.items():
            other._frames[name][:, depth - kept:] = frames[:, self.depth - kept:]
            other._frames[name][:, :depth - kept] = frames[:, self.depth - kept:self.depth - kept + 1]
        return other
