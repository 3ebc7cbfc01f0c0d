"""A training whose disk fills up, that shares its run folder, or that starts from hostile files.

ENOSPC is injected at the first write of every kind a resumed training makes (its run folder's
lock, ``config.yaml``, ``metrics.csv``, ``log.txt``, the checkpoint, ``last_checkpoint``,
``curves.png``; each operation on each), EACCES at one write of each file: the run stops with one
line saying what ran out and how to resume, the checkpoint it resumed from is untouched, and
``--resume`` then ends with the weights of a run that never failed, bit for bit.
"""

from __future__ import annotations

import errno
import os
import pickle
import shutil
import socket
import subprocess
import sys
from functools import partial
from pathlib import Path

import pytest
import torch

from tests.data.synthetic_records import build_synthetic_records
from tests.engine.test_train import FAST as TRAIN_FAST
from tests.faults.outputs import FAULTS, bytes_lost, finished_files, one_line_error
from usl.cli.train import main

FAST = [
    *TRAIN_FAST,
    "train.batch_size=4",
    "train.checkpoint_every=1",
    "train.log_every=1",
    "val.period=0",
]
CHECKPOINT_1 = "checkpoints/model_0000001.pt"


@pytest.fixture(scope="module")
def records(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return build_synthetic_records(tmp_path_factory.mktemp("records") / "records", num_scenes=4, num_views=4, size=32)


def train(records: Path, out: Path, *overrides: str) -> int:
    return main(["--config", "tiny", "--out", str(out), f"data.root={records}", *FAST, *overrides])


def resume(out: Path) -> int:
    return main(["--resume", "--out", str(out), "optim.max_iter=2"])


def weights(run: Path) -> dict[str, torch.Tensor]:
    return torch.load(run / "checkpoints" / "model_0000002.pt", map_location="cpu", weights_only=True)["model"]


@pytest.fixture(scope="module")
def one_iteration(records: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A run stopped after its first iteration's checkpoint."""
    out = tmp_path_factory.mktemp("run") / "run"
    assert train(records, out, "optim.max_iter=1") == 0
    return out


@pytest.fixture(scope="module")
def reference(one_iteration: Path, tmp_path_factory: pytest.TempPathFactory) -> dict[str, torch.Tensor]:
    """The weights at iteration 2 of that run resumed without a fault."""
    out = tmp_path_factory.mktemp("reference") / "run"
    shutil.copytree(one_iteration, out)
    assert resume(out) == 0
    return weights(out)


# EACCES at one write of each file; ENOSPC at the first write of every kind (operation and file).
ACCESS_SITES = (
    "new folder (owners)",  # taking the run folder
    "file write (metrics.csv)",
    "file write (model_N.pt)",  # inside torch.save, which wraps the OSError in its own RuntimeError
    "file write (last_checkpoint)",
    "rename into place (curves.png)",  # after the last checkpoint, while the run closes
)


@pytest.mark.parametrize(("code", "fault"), FAULTS)
def test_every_kind_of_write_of_a_training_fails_cleanly(
    code, fault, one_iteration, reference, tmp_path, write_faults, fail_write, capsys, fault_tally
):
    out = tmp_path / "count"
    shutil.copytree(one_iteration, out)
    counting = write_faults()
    assert resume(out) == 0
    capsys.readouterr()
    sites = dict.fromkeys(counting.sites) if code == errno.ENOSPC else ACCESS_SITES
    assert set(ACCESS_SITES) <= set(counting.sites)
    for site in sites:
        position = counting.sites.index(site)
        out = tmp_path / f"fault-{position}"
        shutil.copytree(one_iteration, out)
        before = finished_files(out)
        fail_write(position, code, f"training: {site}", partial(resume, out))
        message = one_line_error(capsys.readouterr().err)
        assert fault in message and f"usl-train --resume --out {out}" in message, message
        assert (out / CHECKPOINT_1).read_bytes() == before[CHECKPOINT_1]
        assert resume(out) == 0
        capsys.readouterr()
        resumed = weights(out)
        for name, value in reference.items():
            assert torch.equal(value, resumed[name]), (site, name)
        assert not [p for p in (out / "checkpoints").iterdir() if ".tmp-" in p.name]
        lost = bytes_lost({CHECKPOINT_1: before[CHECKPOINT_1]}, finished_files(out))
        fault_tally.bytes_lost += lost
        fault_tally.survived += lost == 0


def test_a_full_disk_during_training_is_one_line_and_resume_finishes(
    small_disk, one_iteration, reference, capsys, fault_tally
):
    checkpoint = (one_iteration / CHECKPOINT_1).stat().st_size
    disk = small_disk.mount(sum(p.stat().st_size for p in one_iteration.rglob("*") if p.is_file()) + checkpoint // 2)
    out = disk / "run"
    shutil.copytree(one_iteration, out)
    assert resume(out) == 2
    fault_tally.tried += 1
    message = one_line_error(capsys.readouterr().err)
    assert f"{out}: no space left on the device (errno 28)" in message and "--resume" in message
    small_disk.remount(disk, f"size={8 * checkpoint + (1 << 22)}")
    assert resume(out) == 0
    resumed = weights(out)
    assert all(torch.equal(value, resumed[name]) for name, value in reference.items())
    fault_tally.survived += 1


TRAIN_ARGS = ["-m", "usl.cli.train", "--config", "tiny"]


def test_two_trainings_on_one_folder_one_wins_the_other_names_it(records, tmp_path, fault_tally):
    out = tmp_path / "shared"
    argv = [sys.executable, *TRAIN_ARGS, "--out", str(out), f"data.root={records}", *FAST, "optim.max_iter=3"]
    runs = [subprocess.Popen([*argv, f"train.seed={seed}"], stderr=subprocess.PIPE, text=True) for seed in (1, 2)]
    results = [(run.wait(), run.stderr.read()) for run in runs]
    codes = sorted(code for code, _ in results)
    fault_tally.tried += 1
    assert codes == [0, 2], results
    winner, loser = (runs[0], runs[1]) if results[0][0] == 0 else (runs[1], runs[0])
    message = one_line_error(results[runs.index(loser)][1])
    assert f"{out}: usl-train is already writing here (pid {winner.pid} on {socket.gethostname()}" in message
    seed = torch.load(out / "checkpoints" / "model_0000003.pt", weights_only=True)["config"]["train"]["seed"]
    assert (out / "config.yaml").read_text().count(f"seed: {seed}") == 1, "config and weights are the winner's"
    assert not (out / ".lock").exists()
    fault_tally.survived += 1


KILLED_IN_TORCH_SAVE = """
import os, signal, sys, torch
real_save = torch.save
def dies_half_way(obj, f, *args, **kwargs):
    if "model_0000002" in str(getattr(f, "name", f)):
        f.write(b"x" * 4096)
        os.kill(os.getpid(), signal.SIGKILL)
    return real_save(obj, f, *args, **kwargs)
torch.save = dies_half_way
from usl.cli.train import main
sys.exit(main(sys.argv[1:]))
"""


def test_a_training_killed_while_saving_leaves_a_temp_file_that_resume_reaps(one_iteration, reference, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(one_iteration, out)
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_IN_TORCH_SAVE, "--resume", "--out", str(out), "optim.max_iter=2"]
    )
    assert killed.returncode == -9
    assert [p.name for p in (out / "checkpoints").iterdir() if ".tmp-" in p.name]
    assert resume(out) == 0
    assert not [p.name for p in (out / "checkpoints").iterdir() if ".tmp-" in p.name]
    resumed = weights(out)
    assert all(torch.equal(value, resumed[name]) for name, value in reference.items())


class RunsCode:
    def __reduce__(self):
        return (os.system, ("touch PWNED",))


def hostile_weights(tmp_path: Path) -> dict[str, tuple[Path, str]]:
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"not a torch file" * 64)
    torch_code = tmp_path / "code.pth"
    torch.save({"model": RunsCode()}, torch_code)
    pickle_code = tmp_path / "code.pkl"
    pickle_code.write_bytes(pickle.dumps({"model": RunsCode()}))
    return {
        "missing": (tmp_path / "absent.pth", "does not exist"),
        "garbage": (garbage, "could not be read"),
        "code in a torch file": (torch_code, "refused"),
        "code in a pickle": (pickle_code, "refusing to load"),
    }


@pytest.mark.parametrize("case", ["missing", "garbage", "code in a torch file", "code in a pickle"])
def test_a_bad_init_weights_file_is_one_line_and_runs_nothing(case, records, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    path, expected = hostile_weights(tmp_path)[case]
    assert train(records, tmp_path / "run", "optim.max_iter=1", f"model.init_weights={path}") == 2
    message = one_line_error(capsys.readouterr().err)
    assert str(path) in message and expected in message, message
    assert not (tmp_path / "PWNED").exists()


def test_a_checkpoint_that_holds_code_is_refused_in_one_line(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    checkpoint = tmp_path / "model.pt"
    torch.save({"model": RunsCode(), "config": {}}, checkpoint)
    assert main(["--resume", str(checkpoint)]) == 2
    message = one_line_error(capsys.readouterr().err)
    assert str(checkpoint) in message and "refused" in message and "weights_only" not in message, message
    assert not (tmp_path / "PWNED").exists()
