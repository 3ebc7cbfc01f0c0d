"""torch.distributed plumbing: one process per GPU (or CPU process) launched by torchrun.

``init_distributed`` reads torchrun's environment (RANK, WORLD_SIZE, LOCAL_RANK, LOCAL_WORLD_SIZE,
MASTER_ADDR, MASTER_PORT), so the same command works on one machine or several
(``torchrun --nnodes N --nproc_per_node G --rdzv_backend c10d --rdzv_endpoint HOST:PORT --rdzv_id ID
-m usl.cli.train ...`` on each machine: the c10d rendezvous numbers the machines as they join).
NCCL on CUDA, gloo on CPU. Without torchrun it is a plain single process.
"""

from __future__ import annotations

import hashlib
import os
import sys
from dataclasses import dataclass
from typing import Any

import torch
import torch.distributed as dist

from usl.errors import UslError


@dataclass(frozen=True)
class DistInfo:
    rank: int
    world_size: int
    local_rank: int
    device: torch.device

    @property
    def is_main(self) -> bool:
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1


def choose_device(preference: str, local_rank: int, local_world_size: int | None = None) -> torch.device:
    """This process's device: one GPU per process on its machine, or the CPU.

    NCCL cannot run two processes on one GPU. torchrun starts every process of a machine with the
    same visible GPUs and says how many there are (``local_world_size``), so ``auto`` takes CUDA only
    when each gets a GPU of its own; otherwise (e.g. the main job's two processes on a laptop with
    one GPU) it trains on the CPU with gloo. An explicit ``cuda`` that cannot be honoured fails.
    Without ``local_world_size`` (a launcher that binds each process to its GPUs itself), process
    ``local_rank`` takes visible GPU ``local_rank`` modulo their number.
    """
    gpus = torch.cuda.device_count() if torch.cuda.is_available() else 0
    if preference == "cuda" and gpus == 0:
        raise UslError("train.device=cuda but CUDA is not available")
    shared = local_world_size is not None and local_world_size > gpus
    if preference == "cuda" and shared:
        raise UslError(
            f"train.device=cuda: {local_world_size} processes on this machine but {gpus} CUDA device(s); "
            "NCCL needs a GPU per process (launch one process per GPU, or set train.device=cpu)"
        )
    if preference in ("auto", "cuda") and gpus and not shared:
        return torch.device("cuda", local_rank % gpus)
    return torch.device("cpu")


def init_distributed(device_preference: str = "auto") -> DistInfo:
    world_size = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local_rank = int(os.environ.get("LOCAL_RANK", "0"))
    local_world_size = int(os.environ["LOCAL_WORLD_SIZE"]) if "LOCAL_WORLD_SIZE" in os.environ else None
    device = choose_device(device_preference, local_rank, local_world_size)
    if device.type == "cpu" and device_preference == "auto" and torch.cuda.is_available() and rank == 0:
        print(
            f"usl-train: train.device=auto: {local_world_size} processes on this machine share "
            f"{torch.cuda.device_count()} GPU(s), and NCCL needs one each: training on the CPU",
            file=sys.stderr,
        )
    if device.type == "cuda":
        torch.cuda.set_device(device)
    if world_size > 1 and not dist.is_initialized():
        dist.init_process_group(
            backend="nccl" if device.type == "cuda" else "gloo", device_id=device if device.type == "cuda" else None
        )
    return DistInfo(rank, world_size, local_rank, device)


def shutdown_distributed() -> None:
    if dist.is_available() and dist.is_initialized():
        dist.destroy_process_group()


def _active() -> bool:
    return dist.is_available() and dist.is_initialized() and dist.get_world_size() > 1


def barrier() -> None:
    if _active():
        dist.barrier()


def all_reduce_min(values: torch.Tensor) -> torch.Tensor:
    out = values.clone()
    if _active():
        dist.all_reduce(out, op=dist.ReduceOp.MIN)
    return out


def all_gather_objects(obj: Any) -> list[Any]:
    """Every process's ``obj``, in rank order (a one-element list when not distributed)."""
    if not _active():
        return [obj]
    gathered: list[Any] = [None] * dist.get_world_size()
    dist.all_gather_object(gathered, obj)
    return gathered


def parameter_digest(module: torch.nn.Module) -> str:
    """SHA-256 of ``module``'s parameter names and values (in NCHW order, whatever their layout)."""
    digest = hashlib.sha256()
    for name, param in module.named_parameters():
        digest.update(name.encode())
        digest.update(param.detach().contiguous().reshape(-1).view(torch.uint8).cpu().numpy().tobytes())
    return digest.hexdigest()


def replica_digests(module: torch.nn.Module) -> list[str]:
    """Every process's ``parameter_digest`` of its replica, in rank order; a ``UslError`` when they differ.

    DDP keeps the replicas identical (the same start, averaged gradients, steps skipped together),
    and a checkpoint holds process 0's weights as the model's: a replica that drifted away is a bug
    to stop at, not one to train on. Every process gets the same list, so all of them stop together.
    """
    digests = all_gather_objects(parameter_digest(module))
    drifted = [rank for rank, digest in enumerate(digests) if digest != digests[0]]
    if drifted:
        raise UslError(f"the weights of process(es) {drifted} differ from process 0's: the DDP replicas drifted apart")
    return digests
