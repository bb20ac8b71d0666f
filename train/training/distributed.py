"""Multi-process training through torchrun (DDP): gloo on CPU, NCCL on CUDA.

Each process takes an equal, contiguous shard of the *global* batch, so with DDP's gradient averaging
the update equals a single-process step on the whole global batch (the loss is a per-sample mean).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import torch
import torch.distributed as dist

from toolkit.errors import ToolkitError


@dataclass
class DistInfo:
    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    device: str = "cpu"

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def enabled(self) -> bool:
        return self.world_size > 1


def env_count(name: str, default: int, low: int, high: int) -> int:
    """An integer environment variable (torchrun's) in [low, high]; one ``ToolkitError`` naming it otherwise."""
    text = os.environ.get(name, "").strip() or str(default)
    if not re.fullmatch(r"[+-]?\d{1,9}", text) or not low <= int(text) <= high:
        raise ToolkitError(f"environment variable {name}: expected an integer in [{low}, {high}], got {text!r}")
    return int(text)


def world_size() -> int:
    """torchrun's ``WORLD_SIZE`` (1 when not launched by it), checked."""
    return env_count("WORLD_SIZE", 1, 1, 65536)


def is_main_process() -> bool:
    """Whether this is torchrun's rank 0 (or a single process): the one that logs and writes."""
    world = world_size()
    return world == 1 or env_count("RANK", 0, 0, world - 1) == 0  # RANK means nothing outside torchrun


def init_distributed(device: str = "auto") -> DistInfo:
    """Initialise the process group when launched by torchrun (WORLD_SIZE > 1); else a single process."""
    world = world_size()
    rank = env_count("RANK", 0, 0, world - 1)
    local = env_count("LOCAL_RANK", 0, 0, 1023)
    use_cuda = torch.cuda.is_available() if device == "auto" else device.startswith("cuda")
    dev = f"cuda:{local}" if use_cuda else "cpu"
    if world > 1 and not dist.is_initialized():
        dist.init_process_group(backend="nccl" if use_cuda else "gloo")
        if use_cuda:
            torch.cuda.set_device(local)
    return DistInfo(rank, world, local, dev)


def shard(global_batch: int, info: DistInfo) -> slice:
    """This process's slice of a global batch of ``global_batch`` samples."""
    if global_batch % info.world_size:
        raise ToolkitError(
            f"global batch {global_batch} is not divisible by the {info.world_size} processes; "
            "choose a multiple so every process gets the same shard size"
        )
    per = global_batch // info.world_size
    return slice(info.rank * per, (info.rank + 1) * per)


def wrap(module: torch.nn.Module, info: DistInfo) -> torch.nn.Module:
    """DDP-wrap ``module`` when running distributed (identity otherwise)."""
    if not info.enabled:
        return module
    from torch.nn.parallel import DistributedDataParallel as DDP

    return DDP(module, device_ids=[info.local_rank] if info.device.startswith("cuda") else None)


def all_ranks(ok: bool, info: DistInfo) -> bool:
    """True when ``ok`` holds on every rank (one all-reduce): a rank that is about to stop makes all stop
    together, instead of leaving its peers blocked in the next collective."""
    if not info.enabled:
        return ok
    flag = torch.tensor([1 if ok else 0], dtype=torch.int32, device=info.device)
    dist.all_reduce(flag, op=dist.ReduceOp.MIN)
    return bool(flag.item())


def average_gradients(params: list[torch.nn.Parameter], info: DistInfo) -> None:
    """Average ``.grad`` over the ranks in place, what DDP's reducer does, for training loops whose modules are
    called through methods other than ``forward`` (the Gaussian stage calls ``renderer.training_forward``).

    With equal shards of a global batch and per-sample mean losses, the result is the gradient of the whole
    batch. A parameter with no gradient on any rank keeps ``None`` (Adam then skips it, as one process
    would); one with a gradient on some ranks only gets zeros on the others. Two small all-reduces: which
    parameters have gradients, then all gradients in one flat buffer."""
    if not info.enabled or not params:
        return
    has = torch.tensor([p.grad is not None for p in params], dtype=torch.int32, device=info.device)
    dist.all_reduce(has, op=dist.ReduceOp.MAX)
    live = [p for p, h in zip(params, has.tolist()) if h]
    if not live:
        return
    for p in live:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    flat = torch.cat([p.grad.reshape(-1) for p in live])
    dist.all_reduce(flat)
    flat /= info.world_size
    offset = 0
    for p in live:
        n = p.grad.numel()
        p.grad.copy_(flat[offset:offset + n].view_as(p.grad))
        offset += n


def barrier(info: DistInfo) -> None:
    if info.enabled:
        dist.barrier()


def cleanup(info: DistInfo) -> None:
    """Tear down the process group; all ranks meet first so none exits while a peer still talks to it
    (a rank leaving early made gloo abort its peers with SIGABRT)."""
    if info.enabled and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()
