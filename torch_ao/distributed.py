"""Data-parallel ranks: the process group under ``torchrun`` and the few collectives a fit needs.

Every helper works without a process group (one process: rank 0 of 1, the collectives return their
input), so the same code runs under ``python`` and under ``torchrun --nproc_per_node N``.

* :func:`init_from_environment` starts the process group from ``torchrun``'s environment (``WORLD_SIZE``,
  ``RANK``, ``LOCAL_RANK``): ``nccl`` when the fit runs on CUDA, else ``gloo``.
* :func:`shard` is the part of a list of indices a rank works on (round robin: rank ``r`` of ``W`` takes
  items ``r, r + W, ...``).
* :func:`sum_over_ranks` sums a float64 vector over the ranks in rank order on every rank, so every rank
  holds the same bits (and takes the same step) whatever the backend's reduction order.
"""
from __future__ import annotations

import os
import time

import torch
import torch.distributed as dist

__all__ = ["is_distributed", "rank", "world_size", "is_main", "init_from_environment", "finish", "rank_device",
           "shard", "sum_over_ranks", "gather_objects", "broadcast_object"]


def is_distributed() -> bool:
    """Whether a process group of more than one rank is running."""
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def rank() -> int:
    """This process's rank (0 without a process group)."""
    return dist.get_rank() if is_distributed() else 0


def world_size() -> int:
    """The number of ranks (1 without a process group)."""
    return dist.get_world_size() if is_distributed() else 1


def is_main() -> bool:
    """Whether this process is rank 0, the one that writes files and prints reports."""
    return rank() == 0


def init_from_environment(device: str | torch.device = "cpu") -> bool:
    """Start the process group when ``torchrun`` launched more than one process (``WORLD_SIZE > 1``);
    returns whether this run is data-parallel. The backend is ``nccl`` for a CUDA ``device`` (each rank
    on GPU ``LOCAL_RANK``), else ``gloo``; CPU ranks share the cores (``torch.set_num_threads``)."""
    if int(os.environ.get("WORLD_SIZE", "1")) <= 1:
        return False
    if not dist.is_initialized():
        cuda = torch.device(device).type == "cuda"
        if cuda:
            torch.cuda.set_device(int(os.environ.get("LOCAL_RANK", "0")))
        else:
            torch.set_num_threads(max(1, (os.cpu_count() or 1) // int(os.environ["WORLD_SIZE"])))
        dist.init_process_group("nccl" if cuda else "gloo")
    return is_distributed()


def finish(completed: bool = True) -> None:
    """End the process group :func:`init_from_environment` started (nothing without one). A rank that
    ``completed`` first waits for the others (a barrier), ends its group, and then waits until every rank has
    ended its own (a counter in the rendezvous store): a rank must not close its connections while a peer still
    uses them, which gloo answers by aborting that peer's process ("terminate called without an active
    exception"). A rank that failed does not wait (``torchrun`` stops the others).

    A group that ``DistributedDataParallel`` wrapped is not freed here: DDP keeps references to it, so gloo's
    worker threads live on into the interpreter's shutdown, where one that drops a finished collective's tensors
    aborts the process the same way. Such a script ends its ranks with ``os._exit`` once its files are written
    (``training_examples/train_thickness_net.py``)."""
    if not dist.is_initialized():
        return
    if not completed:
        dist.destroy_process_group()
        return
    store, world = dist.distributed_c10d._get_default_store(), dist.get_world_size()
    dist.barrier()
    dist.destroy_process_group()
    try:  # (the store outlives the group: torchrun's agent keeps it; at worst the wait ends at its deadline)
        store.add("torch_ao/finished", 1)
        deadline = time.monotonic() + 60.0
        while store.add("torch_ao/finished", 0) < world and time.monotonic() < deadline:
            time.sleep(0.01)
    except RuntimeError:
        pass


def rank_device(device: str | torch.device) -> torch.device:
    """``device`` as this rank uses it: a CUDA device becomes GPU ``LOCAL_RANK`` under ``torchrun``."""
    device = torch.device(device)
    if device.type == "cuda" and is_distributed():
        return torch.device("cuda", int(os.environ.get("LOCAL_RANK", "0")))
    return device


def shard(items: list, rank_: int | None = None, world: int | None = None) -> list:
    """The items rank ``rank_`` of ``world`` works on: ``items[rank_::world]`` (this process's by default)."""
    rank_ = rank() if rank_ is None else rank_
    world = world_size() if world is None else world
    return items[rank_::world]


def _collective_device() -> torch.device:
    return torch.device("cuda", torch.cuda.current_device()) if dist.get_backend() == "nccl" else torch.device("cpu")


def sum_over_ranks(values: torch.Tensor) -> torch.Tensor:
    """The sum over the ranks of a 1-D ``values`` (float64 on any device), added in rank order on every
    rank (an all-gather, then a local sum), so each rank gets the same bits. Without a process group,
    ``values`` itself."""
    if not is_distributed():
        return values
    flat = values.detach().to(_collective_device(), torch.float64).contiguous()
    parts = [torch.empty_like(flat) for _ in range(world_size())]
    dist.all_gather(parts, flat)
    total = parts[0].clone()
    for part in parts[1:]:
        total += part
    return total.to(values.device)


def gather_objects(obj) -> list:
    """``[obj of rank 0, obj of rank 1, ...]`` on every rank (picklable objects; ``[obj]`` without a process group)."""
    if not is_distributed():
        return [obj]
    out = [None] * world_size()
    dist.all_gather_object(out, obj)
    return out


def broadcast_object(obj, src: int = 0):
    """Rank ``src``'s ``obj`` on every rank (``obj`` itself without a process group)."""
    if not is_distributed():
        return obj
    box = [obj]
    dist.broadcast_object_list(box, src=src)
    return box[0]
