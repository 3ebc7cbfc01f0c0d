"""train.device under torchrun: one GPU per process, or the CPU (NCCL cannot share a GPU)."""

import pytest
import torch

from usl.engine.distributed import choose_device
from usl.errors import UslError


@pytest.fixture
def gpus(monkeypatch):
    """Pretend this machine has N CUDA devices (CI has none)."""

    def set_count(count: int) -> None:
        monkeypatch.setattr(torch.cuda, "is_available", lambda: count > 0)
        monkeypatch.setattr(torch.cuda, "device_count", lambda: count)

    return set_count


@pytest.mark.parametrize(
    "count, procs, expected",
    [
        (0, 1, ["cpu"]),
        (1, 1, ["cuda:0"]),
        (2, 2, ["cuda:0", "cuda:1"]),
        (4, 2, ["cuda:0", "cuda:1"]),
        (1, 2, ["cpu", "cpu"]),  # the main job's two processes on a one-GPU laptop
        (2, 3, ["cpu", "cpu", "cpu"]),
    ],
)
def test_auto_takes_a_gpu_per_process_or_else_the_cpu(gpus, count, procs, expected):
    gpus(count)
    assert [str(choose_device("auto", rank, procs)) for rank in range(procs)] == expected


def test_without_torchrun_s_count_each_process_takes_its_visible_gpu(gpus):
    """A launcher that binds each process to its own GPU (each sees one) sets no LOCAL_WORLD_SIZE."""
    gpus(1)
    assert [str(choose_device("auto", rank)) for rank in range(2)] == ["cuda:0", "cuda:0"]
    gpus(2)
    assert [str(choose_device("cuda", rank)) for rank in range(2)] == ["cuda:0", "cuda:1"]


def test_cpu_stays_on_the_cpu_whatever_the_gpus(gpus):
    gpus(2)
    assert choose_device("cpu", 1, 2) == torch.device("cpu")


def test_explicit_cuda_gets_its_gpu_or_a_clear_error(gpus):
    gpus(2)
    assert choose_device("cuda", 1, 2) == torch.device("cuda", 1)
    gpus(1)
    with pytest.raises(UslError, match=r"train.device=cuda: 2 processes on this machine but 1 CUDA device"):
        choose_device("cuda", 0, 2)
    gpus(0)
    with pytest.raises(UslError, match="CUDA is not available"):
        choose_device("cuda", 0, 1)
