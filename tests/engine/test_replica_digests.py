"""``replica_digests``: two gloo processes whose replicas agree get the same digests; when they
differ, both stop with one error (neither waits for the other)."""

import json
import os
import socket
from pathlib import Path

import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from usl.engine.distributed import parameter_digest, replica_digests
from usl.errors import UslError


def _replica(seed: int) -> nn.Module:
    torch.manual_seed(seed)
    return nn.Conv2d(3, 4, 3).to(memory_format=torch.channels_last)


def _rank(rank: int, port: int, out: str) -> None:
    """Digests of a replica equal in both ranks, then of one seeded by the rank."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=2)
    try:
        results = []
        for seed in (0, rank):
            try:
                results.append({"digests": replica_digests(_replica(seed))})
            except UslError as exc:
                results.append({"error": str(exc)})
        Path(out, f"{rank}.json").write_text(json.dumps(results))
    finally:
        dist.destroy_process_group()


def test_equal_replicas_give_every_rank_the_same_digests_and_drifted_ones_stop_both(tmp_path):
    with socket.socket() as s:  # a free port (the spawned processes import this module: keep it light)
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.start_processes(_rank, args=(port, str(tmp_path)), nprocs=2, start_method="spawn")
    equal, drifted = zip(*(json.loads((tmp_path / f"{rank}.json").read_text()) for rank in range(2)), strict=True)
    torch.manual_seed(0)
    expected = parameter_digest(nn.Conv2d(3, 4, 3))  # NCHW here: the digest reads values, not layout
    assert list(equal) == [{"digests": [expected, expected]}] * 2
    assert drifted[0] == drifted[1] and "process(es) [1] differ from process 0's" in drifted[0]["error"]
