"""What the learner's algorithms share: the policy spec a config trains, Adam, bfloat16 detection,
and replay arrays as tensors."""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
import torch

from l2r import encoders
from l2r.policy import ACTIVATIONS, GAUSSIAN, check_spec
from l2r.protocol.limits import MAX_FRAME_STACK
from l2r.protocol.observations import ObservationSpec


def policy_spec(config, observation: ObservationSpec | int, act_dim: int, kind: str = GAUSSIAN,
                frame_stack: int = 1, encoder: dict | None = None, residual: int | None = None) -> dict:
    """The architecture spec of the policy a config (SACConfig, PPOConfig, TD3Config) trains, sent
    with the weights. `observation`: the spec of the observation, or the width of the float32
    vector; `frame_stack` and `encoder` (its sizes) count for image observations alone; `residual`,
    where the state holds the last action of a residual deterministic policy (l2r.policy)."""
    if isinstance(observation, int):
        observation = ObservationSpec.vector(observation)
    return check_spec({**observation.policy_entries(), "frame_stack": frame_stack, "encoder": encoder or {},
                       "act_dim": act_dim, "hidden": list(config.hidden),
                       "activation": config.activation, "layer_norm": config.layer_norm,
                       "relative_x": config.relative_x, "normalize_obs": config.normalize_obs, "kind": kind,
                       **({} if residual is None else {"residual": residual})})


def check_off_policy(config) -> None:
    """The checks SACConfig and TD3Config share (their networks, discount, Polyak rate, precision,
    frame stack and image encoder); ValueError saying what is wrong."""
    if config.activation not in ACTIVATIONS:
        raise ValueError(f"activation must be one of {sorted(ACTIVATIONS)}, got {config.activation!r}")
    if not 0.0 <= config.gamma <= 1.0 or not 0.0 < config.tau <= 1.0:
        raise ValueError(f"need 0 <= gamma <= 1 and 0 < tau <= 1, got {config.gamma}, {config.tau}")
    if config.precision not in ("auto", "float32", "bfloat16"):
        raise ValueError(f"precision must be auto, float32 or bfloat16, got {config.precision!r}")
    if config.encoder not in encoders.IMAGE_VIEWS:
        raise ValueError(f"encoder must be one of {sorted(encoders.IMAGE_VIEWS)}, got {config.encoder!r}")
    if not 1 <= config.frame_stack <= MAX_FRAME_STACK or config.augment_pad < 0:
        raise ValueError(f"need 1 <= frame_stack <= {MAX_FRAME_STACK} and augment_pad >= 0, got "
                         f"{config.frame_stack} and {config.augment_pad}")


def adam(params, lr: float, device: torch.device, eps: float = 1e-8) -> torch.optim.Adam:
    # The fused kernel exists on CPU and CUDA; it is the fastest Adam on both. Capturable on CUDA:
    # its step count and bias correction stay on the GPU, so a CUDA graph can hold the step.
    return torch.optim.Adam(params, lr=lr, eps=eps, fused=device.type in ("cpu", "cuda"),
                            capturable=device.type == "cuda")


def load_adam_state(opt: torch.optim.Optimizer, saved: dict) -> None:
    """Load a saved Adam state, keeping this optimizer's `capturable` (a saved one carries its own):
    a checkpoint from a CPU then resumes on a GPU with an Adam a CUDA graph can hold. An optimizer
    without the flag (ACKTR's SGD) loads as saved."""
    capturable = [group.get("capturable") for group in opt.param_groups]
    opt.load_state_dict(saved)
    for group, flag in zip(opt.param_groups, capturable):
        if flag is not None:
            group["capturable"] = flag


def bfloat16_pays(device: torch.device) -> bool:
    """Whether bfloat16 matmuls make an update faster on `device`: on a CPU with native bfloat16
    (AVX512-BF16 or AMX), where the matmuls are the update's cost. Not on CUDA: at these widths a
    GPU update waits on kernel launches, and autocast's casts add launches (float32 measured 1.3x
    faster on an H100, docs/performance.md). Not where bfloat16 is emulated."""
    return device.type == "cpu" and torch.ops.mkldnn._is_mkldnn_bf16_supported()


@dataclass
class Transitions:
    """Transitions as tensors, actions in the policy's (-1, 1) space; each algorithm's Batch adds its own."""

    obs: torch.Tensor | dict[str, torch.Tensor]
    """The float32 vector (B, width), or observations of image fields: field name -> stacked field
    (B, k*C, H, W) uint8 images, (B, k*width) float32 vectors (`sac.batch_from_frames`)."""
    action: torch.Tensor
    reward: torch.Tensor
    next_obs: torch.Tensor | dict[str, torch.Tensor]
    """The true next observation of each step (the final one where an episode ended)."""
    terminated: torch.Tensor
    """1.0 where the episode ended for real (no bootstrap); time-limit ends stay 0."""


def float_tensor(a: np.ndarray, device: str | torch.device) -> torch.Tensor:
    """A float32 tensor of a replay array on `device` (see `device_tensor`)."""
    return device_tensor(np.asarray(a, np.float32), device)


def device_tensor(a: np.ndarray, device: str | torch.device) -> torch.Tensor:
    """A tensor of a replay array on `device`, in the array's dtype. Decoded messages are read-only
    views; torch wants memory it may write, so on a CPU those are copied once. For a GPU the array
    is copied once, straight into pinned memory (not first into writable memory: a batch of
    84 x 84 frames at n-step 3 is 31 MB, and the learner's host work bounds DrQ-v2 on a GPU,
    docs/performance.md), and the copy to the device is queued behind the device's work without
    the host waiting for it."""
    if torch.device(device).type == "cuda":
        pinned = torch.empty(a.shape, dtype=torch_dtype(a.dtype), pin_memory=True)
        np.copyto(pinned.numpy(), a)
        return pinned.to(device, non_blocking=True)
    return torch.from_numpy(np.require(a, requirements="W")).to(device)


@functools.cache
def torch_dtype(dtype: np.dtype) -> torch.dtype:
    """torch's dtype of numpy's `dtype`."""
    return torch.from_numpy(np.empty(0, dtype)).dtype
