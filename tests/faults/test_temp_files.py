"""Temp files of writers killed mid-write are removed by a later run once their writer is gone."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

from tests.faults.outputs import temp_files
from tests.faults.small_build import build

REPO = Path(__file__).parents[2]
KILLED_WHILE_CREATING_THE_BUILD = """
import os, signal, sys
os.link = lambda *args, **kwargs: os.kill(os.getpid(), signal.SIGKILL)  # dies just before build.json exists
from tests.faults.small_build import build
build(sys.argv[1])
"""


def test_a_build_killed_before_build_json_leaves_a_temp_file_the_next_run_reaps(tmp_path):
    out = tmp_path / "ds"
    killed = subprocess.run(
        [sys.executable, "-c", KILLED_WHILE_CREATING_THE_BUILD, str(out)],
        env={**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])},
    )
    assert killed.returncode == -9
    assert [Path(p).name.split(".tmp-")[0] for p in temp_files(out)] == [".build.json"]
    assert build(out) == 0
    assert temp_files(out) == []
