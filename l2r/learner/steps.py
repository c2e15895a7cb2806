"""Gradient steps of an algorithm's `update(state, batch, config)`: eager, compiled by
torch.compile (inductor), or captured as CUDA graphs (one launch per batch).

An update of these networks is a few hundred small kernels. On a GPU each launch costs the host
about 10 us, far more than the kernel takes, so an eager update waits on Python and the
dispatcher. Captured as a CUDA graph, `repeat` updates are one launch; inductor fuses the
elementwise work into fewer kernels, on CPU and CUDA.

What an update must do to be compiled and captured (`sac.update` and `td3.update` do):
- no host synchronisation: no `.item()`, `float(tensor)`, `.cpu()`, no tensor made from Python
  data on the device (a graph replays kernels; the host never sees a value);
- no Python branches on tensor values (only on the config and on which batch fields are set);
- no Python counters: `GradientSteps` adds to `state.updates`, and passes an update that steps
  some networks only on some updates (TD3's delayed actor) whether this one does, as a bool;
- no Python values that change between calls (TD3's exploration std is set after the steps);
- optimizers made capturable on CUDA (`common.adam`);
- its state's tensors kept, not replaced, after the first call: a graph holds the addresses it
  was captured with (load a checkpoint before, not after).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Callable

import torch
from torch.utils._triton import has_triton

from l2r.learner.distributed import DeviceUnavailable

COMPILE_MODES = ("auto", "off", "graphs", "inductor", "inductor-graphs")
"""off: eager, one kernel launch per operation. graphs: the eager update's kernels captured as one
CUDA graph (CUDA; no compiler needed). inductor: torch.compile's generated kernels (needs a C++
compiler on CPU, Triton on CUDA). inductor-graphs: both (CUDA). auto: inductor-graphs on CUDA
where Triton is installed, graphs where it is not or the update takes images; off on CPU."""

# Calls run before a capture: they compile (inductor), initialise the optimizers' state and
# settle torch.compile's recompilations; capturing first-call work would record it for good.
WARMUP_CALLS = 3


def resolve_mode(mode: str, device: torch.device, images: bool = False) -> str:
    """What `mode` means on `device` for an update of vector or (`images`) image observations;
    DeviceUnavailable for graphs without CUDA."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode must be one of {', '.join(COMPILE_MODES)}, got {mode!r}")
    if mode == "auto":
        # On CUDA a graph replaces the eager update's ~280 launches (H200: 947 against 112 updates/s)
        # and inductor's fusion cuts the GPU time under it by a third (1,428/s, after ~25 s of
        # compilation at start): docs/performance.md. On CPU the update is bound by its matmuls,
        # which inductor leaves to the same BLAS: it saves 10-15 % of the CPU time but compiles for
        # minutes at start, and needs a C++ compiler, which the CPU image lacks.
        if device.type != "cuda":
            return "off"
        # DrQ-v2's update compiled by inductor gave another critic loss than eager's at the first
        # update on an H200 (2026-11-27; on a CPU it agreed); its eager kernels captured agree.
        return "inductor-graphs" if has_triton() and not images else "graphs"
    if mode.endswith("graphs") and device.type != "cuda":
        raise DeviceUnavailable(f"--compile {mode} captures CUDA graphs: it needs a CUDA device, this learner "
                                f"trains on {device.type}")
    return mode


Update = Callable[..., dict[str, torch.Tensor]]


class GradientSteps:
    """`repeat` gradient steps of `update(state, batch, config)` per call, run as `mode` says, and
    counted in `state.updates`.

    With `policy_delay` (TD3), each step is `update(state, batch, config, actor_step, actor_learns)`,
    actor_step True on every policy_delay-th update of the run, actor_learns from the
    `actor_after`-th on: plain bools, so a compiled update has one version per pair of values and a
    block of `repeat` updates one graph per pattern of them (at most 2 x policy_delay).

    With graphs, the first WARMUP_CALLS calls for a batch shape and pattern run eagerly on a side
    stream; the next captures `repeat` updates on static copies of the batch fields, and every call
    after copies its batch into them and replays the graph. The metrics returned are then the
    graph's own output tensors: read or copy them before the next call, which overwrites them.
    """

    def __init__(self, update: Update, config, mode: str = "off", device: str | torch.device = "cpu",
                 repeat: int = 1, policy_delay: int | None = None, actor_after: int = 0):
        self.config, self.repeat, self.policy_delay, self.actor_after = config, repeat, policy_delay, actor_after
        self.mode = resolve_mode(mode, torch.device(device))
        # fallback_random: random draws by ATen's generator, the same numbers eager draws. Not dynamic:
        # a learner's batches have one shape, and kernels specialised to it are the fastest.
        self._update = (torch.compile(update, dynamic=False, options={"fallback_random": True})
                        if self.mode.startswith("inductor") else update)
        self._graphs: dict[tuple, _Graph] = {}
        self._calls: dict[tuple, int] = {}
        self._state = None

    def __call__(self, state, batch) -> dict[str, torch.Tensor]:
        if self._state is None:
            self._state = state
        elif state is not self._state:  # compiled guards and graphs hold the first state's tensors
            raise ValueError("a GradientSteps runs on the state it first ran on; make one per state")
        pattern = self._pattern(state.updates)
        if self.mode.endswith("graphs"):
            metrics = self._graphed(state, batch, pattern)
        else:
            metrics = self._steps(state, batch, pattern)
        state.updates += self.repeat
        return metrics

    def _pattern(self, updates: int) -> tuple[tuple, ...]:
        """The extra arguments of each of the next `repeat` updates, after `updates` so far."""
        if self.policy_delay is None:
            return ((),) * self.repeat
        return tuple(((updates + step) % self.policy_delay == 0, updates + step > self.actor_after)
                     for step in range(1, self.repeat + 1))

    def _steps(self, state, batch, pattern: tuple[tuple, ...]) -> dict[str, torch.Tensor]:
        for args in pattern:
            metrics = self._update(state, batch, self.config, *args)
        return metrics

    def _graphed(self, state, batch, pattern: tuple[tuple, ...]) -> dict[str, torch.Tensor]:
        key = (_shape(batch), pattern)
        graph = self._graphs.get(key)
        if graph is not None:
            return graph.replay(batch)
        calls = self._calls[key] = self._calls.get(key, 0) + 1
        if calls <= WARMUP_CALLS:
            side = torch.cuda.Stream()
            side.wait_stream(torch.cuda.current_stream())
            with torch.cuda.stream(side):
                metrics = self._steps(state, batch, pattern)
            torch.cuda.current_stream().wait_stream(side)
            return metrics
        graph = self._graphs[key] = _Graph(lambda static: self._steps(state, static, pattern), batch)
        return graph.replay(batch)


class _Graph:
    """A CUDA graph of `steps(batch)` on static copies of a batch's tensors."""

    def __init__(self, steps: Callable, batch):
        self.static = _cloned(batch)
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):  # records the kernels; nothing runs until replay
            self.metrics = steps(self.static)

    def replay(self, batch) -> dict[str, torch.Tensor]:
        # The same fields in the same order: the graph's key holds their names and shapes.
        for (_, static), (_, value) in zip(_fields(self.static), _fields(batch)):
            static.copy_(value, non_blocking=True)
        self.graph.replay()
        return self.metrics


def _cloned(batch):
    """The batch with a copy of each tensor, an image batch's observation maps field by field."""
    def cloned(value):
        return {key: field.clone() for key, field in value.items()} if isinstance(value, Mapping) else value.clone()
    return dataclasses.replace(batch, **{f.name: cloned(getattr(batch, f.name)) for f in dataclasses.fields(batch)
                                         if isinstance(getattr(batch, f.name), (torch.Tensor, Mapping))})


def _fields(batch) -> list[tuple[str, torch.Tensor]]:
    """The batch's tensors by name; an image batch's observations are maps of fields ("obs.pixels")."""
    fields = []
    for f in dataclasses.fields(batch):
        value = getattr(batch, f.name)
        if isinstance(value, torch.Tensor):
            fields.append((f.name, value))
        elif isinstance(value, Mapping):
            fields += [(f"{f.name}.{key}", field) for key, field in value.items()]
    return fields


def _shape(batch) -> tuple:
    """What a captured graph is specific to: which fields are tensors, and their shapes and dtypes."""
    return tuple((name, tuple(value.shape), value.dtype) for name, value in _fields(batch))
