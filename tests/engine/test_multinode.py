"""The multi-machine command of docs/getting_started.md §3, run as two torchrun nodes on this host:
they train one model (one run folder, written once; the same weights in both processes), the
training processes print no warning, and torchrun's agents none before their teardown."""

import hashlib
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import torch

from tests.data.synthetic_records import build_synthetic_records
from tests.engine.test_train import FAST
from usl.engine.checkpoint import load_model, read_checkpoint
from usl.engine.run_log import read_metrics

REPO = Path(__file__).parents[2]
DOCS = REPO / "docs" / "getting_started.md"
MODULE = ["-m", "usl.cli.train"]
NODE_TIMEOUT_S = 300  # for both nodes to finish: 15-35 s on two busy cores, over 120 s on overloaded ones
SIZES = [  # the smallest recipe, shrunk: 4 iterations of 2 images per process
    *FAST,
    "train.device=cpu",  # gloo: on a one-GPU host both nodes would otherwise take GPU 0 (each is alone on its node)
    "train.batch_size=2",
    "optim.max_iter=4",
    "train.log_every=2",
    "train.checkpoint_every=2",
    "val.period=0",
]


def documented_command() -> list[str]:
    """The docs' multi-machine ``torchrun`` command (continuation lines joined), as words."""
    text = DOCS.read_text().replace("\\\n", " ")
    commands = [line for line in text.splitlines() if line.startswith("torchrun ") and "--nnodes" in line]
    assert len(commands) == 1, f"{DOCS}: expected one multi-machine torchrun command, found {commands}"
    return shlex.split(commands[0])


def node_command(endpoint: str, rdzv_id: str, out: Path, records: Path, worker_logs: Path) -> list[str]:
    """The documented command with this host's endpoint, one process per node and the test's sizes;
    the training processes' output goes to files under ``worker_logs`` (torchrun's ``--redirects``),
    so that it is read apart from the agents'."""
    words = documented_command()
    split = words.index(MODULE[0])
    launcher, training = words[1:split], words[split + 2 :]
    assert words[0] == "torchrun" and words[split : split + 2] == MODULE
    flags = dict(zip(launcher[::2], launcher[1::2], strict=True))
    assert len(launcher) == 2 * len(flags) and flags.keys() == {
        "--nnodes",
        "--nproc_per_node",
        "--rdzv_backend",
        "--rdzv_endpoint",
        "--rdzv_id",
    }, launcher
    assert flags["--nnodes"] == "2" and flags["--rdzv_backend"] == "c10d"
    flags.update({"--nproc_per_node": "1", "--rdzv_endpoint": endpoint, "--rdzv_id": rdzv_id})
    flags.update({"--log-dir": str(worker_logs), "--redirects": "3"})
    assert len(training) == 5 and [training[0], training[2], training[4].split("=")[0]] == [
        "--config",
        "--out",
        "data.root",
    ], training
    training = ["--config", "tiny", "--out", str(out), f"data.root={records}", *SIZES]
    # torchrun is the console script of torch.distributed.run; this interpreter's, whatever PATH holds
    return [sys.executable, "-m", "torch.distributed.run", *[w for f in flags.items() for w in f], *MODULE, *training]


# an agent's own logging of a slow rendezvous peer (a busy machine), at any time: both nodes still finish
HEARTBEAT = "failed to send a keep-alive heartbeat to the rendezvous"
# What starts an agent's teardown, once its training processes have exited: the agent hosting the c10d
# store may exit while another still passes the exit barrier (pytorch/pytorch#69520) or closes the
# rendezvous, which then logs one of these, and after it tracebacks and C++ stacks.
TEARDOWN_STARTS = (
    re.compile(r"agent/server/api\.py:\d+\] Error waiting on exit barrier"),
    # the TCPStore client's failed socket call: sendBytes, recvValue, recvVector or recvValueWithTimeout
    re.compile(r"TCPStore\.cpp:\d+\] \[c10d\] \w+ failed on SocketImpl"),
    re.compile(r"has failed to shutdown the rendezvous"),
)


def before_teardown(agent_printed: str) -> str:
    """What an agent printed before its teardown began, less the heartbeat lines of a busy machine.
    The teardown comes after the agent's training processes exited (their output is read apart),
    so what follows its first message is torchrun's, not the training's; both nodes exit 0."""
    kept = []
    for line in agent_printed.splitlines():
        if any(start.search(line) for start in TEARDOWN_STARTS):
            break
        if HEARTBEAT not in line:
            kept.append(line)
    return "\n".join(kept)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def parameter_sha256(state: dict[str, torch.Tensor], names: list[str]) -> str:
    """The test's own digest of saved parameters (names in the model's order, values in NCHW order)."""
    digest = hashlib.sha256()
    for name in names:
        digest.update(name.encode())
        digest.update(state[name].contiguous().reshape(-1).view(torch.uint8).numpy().tobytes())
    return digest.hexdigest()


@pytest.fixture
def start_node(tmp_path):
    """Starts a node in its own process group; every node still running at the end is killed, group and all."""
    nodes: list[subprocess.Popen] = []

    def start(command: list[str], name: str) -> tuple[subprocess.Popen, Path]:
        log = tmp_path / f"{name}.log"
        env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
        with log.open("w") as out:
            nodes.append(
                subprocess.Popen(
                    command, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT, start_new_session=True
                )
            )
        return nodes[-1], log

    yield start
    for node in nodes:
        if node.poll() is None:
            os.killpg(node.pid, signal.SIGKILL)
            node.wait()


def test_two_nodes_train_one_model_into_one_run_folder(tmp_path, start_node):
    records = build_synthetic_records(tmp_path / "records", num_scenes=2, num_views=4, size=48)
    out = tmp_path / "run"
    endpoint, rdzv_id = f"127.0.0.1:{free_port()}", f"usl-test-{uuid.uuid4().hex[:8]}"
    nodes = [
        start_node(node_command(endpoint, rdzv_id, out, records, tmp_path / f"workers{k}"), f"node{k}")
        for k in range(2)
    ]
    deadline = time.monotonic() + NODE_TIMEOUT_S
    while time.monotonic() < deadline and any(node.poll() is None for node, _ in nodes):
        time.sleep(0.2)
    logs = sorted(tmp_path.glob("workers*/**/std*.log"))
    printed = "\n".join(
        f"--- {log.relative_to(tmp_path)}:\n{log.read_text()}" for log in [*(n[1] for n in nodes), *logs]
    )
    codes = [node.poll() for node, _ in nodes]  # None: still running after the deadline (killed by start_node)
    assert codes == [0, 0], f"exit codes {codes} after at most {NODE_TIMEOUT_S} s:\n{printed[-4000:]}"
    # each node's training process: its stdout and stderr, every line of it
    assert [log.relative_to(tmp_path).parts[0] + "/" + log.name for log in logs] == [
        f"workers{k}/{name}" for k in range(2) for name in ("stderr.log", "stdout.log")
    ], logs
    training = "\n".join(log.read_text() for log in logs)
    agents = "\n".join(before_teardown(log.read_text()) for _, log in nodes)
    for word in ("warn", "Traceback", "error"):  # torchrun's banners, DDP's and torch's warnings alike
        assert word.lower() not in training.lower(), training[-3000:]
        assert word.lower() not in agents.lower(), agents[-3000:]

    # one training: one config and log, every logged interval once, checkpoints written once
    assert training.count("usl-train: starting:") == 1 and (out / "config.yaml").is_file()
    assert (out / "log.txt").read_text().count("starting:") == 1
    assert [row["iteration"] for row in read_metrics(out)] == [2, 4]
    assert sorted(p.name for p in (out / "checkpoints").glob("*.pt")) == ["model_0000002.pt", "model_0000004.pt"]

    # of two processes, whose weights are the same: the digest each recorded is the saved weights'
    checkpoint = read_checkpoint(out)
    assert checkpoint["world_size"] == 2 and checkpoint["iteration"] == 4
    names = [name for name, _ in load_model(out)[0].named_parameters()]
    assert checkpoint["replica_sha256"] == [parameter_sha256(checkpoint["model"], names)] * 2


# as agents printed them: a TCPStore read after the store's host exited (torch 2.13, Python 3.11), and
# the exit barrier's logged exception (Python 3.10, torch 2.13), each with what followed it
STORE_READ = (
    "[W1206 05:39:41.415373435 TCPStore.cpp:115] [c10d] {call} failed on SocketImpl(fd=3,"
    " addr=[::ffff:127.0.0.1]:57332, remote=[::ffff:127.0.0.1]:42755): Failed to recv, got 0 bytes.\n"
    "Exception raised from recvBytes at Utils.hpp:787 (most recent call first):\n"
    "frame #0: c10::Error::Error(c10::SourceLocation) + 0x9d\n"
    "<omitting python frames>\n"
    "W1206 05:39:41.911000 26395 dynamic_rendezvous.py:1298] The node 'localhost_26395_0' has failed to shutdown"
    " the rendezvous 'usl-test' due to an error of type RendezvousConnectionError.\n"
)
EXIT_BARRIER = (
    "".join(
        f"E1206 20:44:12.618000 11427 torch/distributed/elastic/agent/server/api.py:1008] {line}\n"
        for line in (
            "Error waiting on exit barrier. Elapsed: 0.01 seconds",
            "Traceback (most recent call last):",
            "torch.distributed.DistNetworkError: Failed to recv, got 0 bytes. Connection was likely closed.",
        )
    )
    + "[W1206 20:44:17.661724367 TCPStore.cpp:106] [c10d] sendBytes failed on SocketImpl(fd=3): Broken pipe\n"
)
SHUTDOWN = STORE_READ.split("\n", 4)[-1]
HEARTBEAT_LINE = (
    "W1206 dynamic_rendezvous.py:1362] The node 'n' has failed to send a keep-alive heartbeat to the rendezvous 'r'\n"
)


@pytest.mark.parametrize(
    "teardown",
    [
        *(STORE_READ.format(call=call) for call in ("sendBytes", "recvValue", "recvVector", "recvValueWithTimeout")),
        EXIT_BARRIER,
        SHUTDOWN,
    ],
)
def test_an_agent_counts_until_its_teardown_starts(teardown):
    """Each message that starts the teardown ends what counts, whatever follows it; before it,
    everything but a busy machine's heartbeat counts."""
    deprecation = "UserWarning: --rdzv_id is deprecated"
    after = "Traceback (most recent call last):\nRuntimeError: anything\n"
    assert before_teardown(f"{HEARTBEAT_LINE}{teardown}{after}") == ""
    assert before_teardown(f"{deprecation}\n{HEARTBEAT_LINE}{teardown}{after}") == deprecation
    assert before_teardown(HEARTBEAT_LINE + deprecation) == deprecation


def test_other_store_warnings_and_agent_records_still_count():
    somaxconn = "[W1206 TCPStore.cpp:334] [c10d] Starting store with 4 workers but somaxconn is 2."
    worker_group = "E1206 20:44:12.618000 11427 torch/distributed/elastic/agent/server/api.py:931] Error in worker group: Traceback"
    for line in (somaxconn, worker_group):
        assert before_teardown(line) == line
