"""Data-parallel training under torchrun: one process per device, gradients averaged every step.

`torchrun --nproc_per_node N -m meshseal.cli train ...` starts N processes; each takes its slice of
every global batch (the batch size in the config is the global one), all draw the same random numbers
for the whole batch, and after the backward pass the gradients are averaged across processes
(`average_gradients`: one all-reduce over all of them, as DistributedDataParallel's buckets do). Batch
normalisation uses statistics over the global batch (`GlobalBatchNorm2d`, which works on the CPU's gloo
backend too, unlike `torch.nn.SyncBatchNorm`), so N processes compute what one process computes at
the same global batch, up to the order of floating-point sums.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch
import torch.distributed as dist
from torch import nn


@dataclass
class World:
    """This process's place among `size` training processes (size 1: not distributed)."""

    rank: int = 0
    size: int = 1
    local_rank: int = 0

    @property
    def distributed(self) -> bool:
        return self.size > 1

    @property
    def main(self) -> bool:
        """The process that logs, validates and writes checkpoints."""
        return self.rank == 0

    def share(self, n: int) -> slice:
        """This process's part of a global batch of `n` (n must divide evenly)."""
        part = n // self.size
        return slice(self.rank * part, (self.rank + 1) * part)


def join(device: str) -> tuple[World, str]:
    """Join the process group torchrun describes in the environment (WORLD_SIZE, RANK, LOCAL_RANK);
    returns the world and this process's device (cuda:LOCAL_RANK for a CUDA run)."""
    size = int(os.environ.get("WORLD_SIZE", "1"))
    if size <= 1:
        return World(), device
    rank, local_rank = int(os.environ["RANK"]), int(os.environ.get("LOCAL_RANK", "0"))
    cuda = torch.device(device).type == "cuda"
    if not dist.is_initialized():
        dist.init_process_group("nccl" if cuda else "gloo")
    if cuda:
        torch.cuda.set_device(local_rank)
        device = f"cuda:{local_rank}"
    return World(rank, size, local_rank), device


def leave(world: World) -> None:
    """Leave the process group once every process has finished (the main one validates and writes
    after the last step while the others are done): no process tears its connections down while
    another may still use them."""
    if world.distributed and dist.is_initialized():
        dist.barrier()
        dist.destroy_process_group()


def average_gradients(parameters: list, world: World) -> None:
    """Replace each parameter's gradient by its mean over the processes (one all-reduce)."""
    if not world.distributed:
        return
    grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in parameters]
    flat = torch.cat([g.reshape(-1) for g in grads])
    dist.all_reduce(flat)
    flat /= world.size
    offset = 0
    for parameter, grad in zip(parameters, grads):
        parameter.grad = flat[offset:offset + grad.numel()].view_as(grad).clone()
        offset += grad.numel()


def average(values: torch.Tensor, world: World) -> torch.Tensor:
    """The mean of a tensor over the processes (the tensor itself when not distributed)."""
    if not world.distributed:
        return values
    values = values.clone()
    dist.all_reduce(values)
    return values / world.size


class GlobalBatchNorm2d(nn.BatchNorm2d):
    """BatchNorm2d whose training statistics are those of the global batch across processes."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if not (self.training and dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1):
            return super().forward(x)
        from torch.distributed.nn.functional import all_reduce

        dtype, x = x.dtype, x.float()
        count = torch.full((1,), x.numel() / x.shape[1], dtype=x.dtype, device=x.device)
        moments = torch.cat([x.sum(dim=(0, 2, 3)), (x * x).sum(dim=(0, 2, 3)), count])
        moments = all_reduce(moments)  # differentiable: the gradient flows to every process's part
        channels = x.shape[1]
        total = moments[-1]
        mean = moments[:channels] / total
        var = (moments[channels:2 * channels] / total - mean * mean).clamp_min(0.0)
        if self.track_running_stats:
            with torch.no_grad():
                self.num_batches_tracked.add_(1)
                # momentum None: a cumulative average, as BatchNorm2d keeps it
                momentum = self.momentum if self.momentum is not None else 1.0 / float(self.num_batches_tracked)
                self.running_mean.mul_(1 - momentum).add_(momentum * mean.detach())
                self.running_var.mul_(1 - momentum).add_(momentum * var.detach() * total / (total - 1))
        shape = (1, channels, 1, 1)
        out = (x - mean.reshape(shape)) / torch.sqrt(var.reshape(shape) + self.eps)
        if self.affine:
            out = out * self.weight.reshape(shape) + self.bias.reshape(shape)
        return out.to(dtype)


def global_batch_norm(module: nn.Module) -> nn.Module:
    """`module` with each BatchNorm2d computing global-batch statistics (same parameters and buffers)."""
    for name, child in module.named_children():
        if type(child) is nn.BatchNorm2d:
            child.__class__ = GlobalBatchNorm2d
        else:
            global_batch_norm(child)
    return module
