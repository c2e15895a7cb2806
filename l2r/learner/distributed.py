"""Device choice and data-parallel set-up for learners (`torch.distributed`).

Every rank samples its own batches; the algorithms' updates average gradients over ranks before
each optimizer step, so ranks that start identical stay identical. Rank 0 publishes weights and
writes checkpoints. Backend: NCCL where every rank has a GPU of its own, else gloo (CPU ranks,
or several ranks sharing one GPU, which NCCL refuses).
"""

from __future__ import annotations

import datetime
import logging
import os

import torch
import torch.distributed as dist

log = logging.getLogger("l2r.learner")


class DeviceUnavailable(RuntimeError):
    """The requested device does not exist here."""


def select_device(name: str, local_rank: int = 0) -> torch.device:
    """'auto' -> CUDA if present, else CPU; 'cuda' without CUDA is an error, not a silent CPU run."""
    if name not in ("auto", "cpu", "cuda"):
        raise ValueError(f"device must be auto, cpu or cuda, got {name!r}")
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise DeviceUnavailable("--device cuda, but this torch sees no CUDA device "
                           f"(torch {torch.__version__}, CUDA build: {torch.version.cuda or 'no'})")
    return torch.device("cuda", local_rank % torch.cuda.device_count())


def ranks_on_this_host(world_size: int) -> int:
    """$LOCAL_WORLD_SIZE, as torchrun sets it; else all ranks (l2r up starts them on one host)."""
    value = os.environ.get("LOCAL_WORLD_SIZE", "")
    if value.isdigit() and int(value) > 0:
        return int(value)
    if value:
        log.warning("$LOCAL_WORLD_SIZE=%r is not a positive whole number: taking all %d ranks as on this host",
                    value, world_size)
    return world_size


def init_distributed(world_size: int, rank: int, dist_url: str | None, device: torch.device,
                     timeout_s: float = 600.0) -> None:
    """Join the process group of `world_size` learners (a no-op when training alone)."""
    if world_size <= 1:
        return
    if not 0 <= rank < world_size:
        raise ValueError(f"rank {rank} not in [0, world size {world_size})")
    own_gpu_each = device.type == "cuda" and torch.cuda.device_count() >= ranks_on_this_host(world_size)
    backend = "nccl" if own_gpu_each else "gloo"
    log.info("rank %d/%d joining %s via %s", rank, world_size, backend, dist_url or "env://")
    dist.init_process_group(backend, init_method=dist_url or "env://", world_size=world_size, rank=rank,
                            timeout=datetime.timedelta(seconds=timeout_s))


def any_rank(flag: bool, device: torch.device) -> bool:
    """True if `flag` is true on any rank (all ranks must call this together)."""
    if not (dist.is_available() and dist.is_initialized()):
        return flag
    t = torch.tensor([1.0 if flag else 0.0], device=device)
    dist.all_reduce(t, op=dist.ReduceOp.MAX)
    return bool(t.item())


def sum_over_ranks(tensor: torch.Tensor) -> None:
    """Sum a tensor over data-parallel ranks, in place (a no-op when training alone)."""
    if dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1:
        dist.all_reduce(tensor)


def average_gradients(params) -> None:
    """Average gradients over data-parallel ranks (a no-op when training alone).

    All gradients travel in one flat buffer: one all-reduce per optimizer step.
    """
    if not (dist.is_available() and dist.is_initialized()) or dist.get_world_size() == 1:
        return
    grads = [p.grad for p in params if p.grad is not None]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= dist.get_world_size()
    offset = 0
    for g in grads:
        g.copy_(flat[offset:offset + g.numel()].view_as(g))
        offset += g.numel()


def broadcast(modules, tensors=()) -> None:
    """Give every data-parallel rank rank 0's module states and tensors, so all start identical."""
    if not (dist.is_available() and dist.is_initialized()):
        return
    with torch.no_grad():
        for module in modules:
            for tensor in module.state_dict().values():
                dist.broadcast(tensor, 0)
        for tensor in tensors:
            dist.broadcast(tensor.data, 0)


def close_distributed() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()
