"""One build of fake scenes as its own process (``python -m tests.records.shared_build OUT VERSION READY_DIR N``).

It waits until N such processes are ready (files in READY_DIR), so that they really build at the
same time, then builds slowly enough to overlap, and prints its summary as JSON.
"""

import json
import os
import sys
import time
from pathlib import Path

from pipelines.common import BuildOptions, ShardPlan, run_build
from tests.records import fake_scenes
from usl.errors import UslError

NUM_SHARDS = 12


def plans():
    units = [(f"scene{i:03d}", i, 2 + i % 3) for i in range(2 * NUM_SHARDS)]
    return [ShardPlan("train", k, units[2 * k : 2 * k + 2]) for k in range(NUM_SHARDS)]


def slow_scene(unit):
    time.sleep(0.1)
    return fake_scenes.build_fake_scene(unit)


def main(out: str, version: str, ready_dir: str, count: str) -> int:
    ready = Path(ready_dir)
    (ready / str(os.getpid())).touch()
    while len(list(ready.iterdir())) < int(count):
        time.sleep(0.01)
    try:
        summary = run_build(
            BuildOptions(Path(out), progress=False),
            fake_scenes.SPEC,
            {"v": int(version)},
            plans(),
            slow_scene,
            {"command": "test"},
        )
    except UslError as exc:
        print(json.dumps({"error": str(exc)}))
        return 2
    print(json.dumps({"built": summary.built_shards, "manifest": summary.manifest_written}))
    return 0


if __name__ == "__main__":
    sys.exit(main(*sys.argv[1:]))
