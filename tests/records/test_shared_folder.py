"""Many processes on one --out: disjoint claims, identical shards, refusal of other arguments,
stale claims taken over, and nothing of a gone process left behind."""

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from pipelines.common import BuildOptions, run_build
from tests.records import fake_scenes
from tests.records.old_writer import write_old_file
from tests.records.shared_build import NUM_SHARDS, plans
from usl.cli.records import main as records_main
from usl.records.claims import host_identity
from usl.records.shards import shard_paths, shard_temp_path
from usl.records.validate import validate_dataset

REPO = Path(__file__).parents[2]  # children import tests.records.* from the repository root


def build(out, version=1, **options):
    return run_build(
        BuildOptions(out, progress=False, **options),
        fake_scenes.SPEC,
        {"v": version},
        plans(),
        fake_scenes.build_fake_scene,
        {"command": "test"},
    )


def shard_checksums(root):
    manifest = json.loads((root / "manifest.json").read_text())
    return [
        (s["frames"]["file"], s["frames"]["sha256"], s["objects"]["sha256"], s["scenes"])
        for e in manifest["splits"].values()
        for s in e["shards"]
    ]


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    root = tmp_path_factory.mktemp("reference") / "ds"
    build(root)
    return root


def start(out, versions, ready):
    ready.mkdir()
    return [
        subprocess.Popen(
            [sys.executable, "-m", "tests.records.shared_build", str(out), str(v), str(ready), str(len(versions))],
            cwd=REPO,
            stdout=subprocess.PIPE,
            text=True,
        )
        for v in versions
    ]


def finish(procs):
    outputs = [p.communicate(timeout=120)[0] for p in procs]
    return [(p.returncode, json.loads(o.strip().splitlines()[-1])) for p, o in zip(procs, outputs, strict=True)]


def leftovers(root):
    """Files no finished build should leave: temp files, spills, claims, owners, scratch."""
    build_dir = root / ".build"
    return (
        [p for p in root.rglob("*") if ".tmp-" in p.name or "scratch-" in p.name]
        + list((build_dir / "claims").iterdir())
        + list((build_dir / "owners").iterdir())
        + (list((build_dir / "spill").iterdir()) if (build_dir / "spill").exists() else [])
    )


def test_three_processes_with_the_same_arguments_share_the_work(reference, tmp_path):
    out = tmp_path / "shared"
    results = finish(start(out, [1, 1, 1], tmp_path / "ready"))
    assert [rc for rc, _ in results] == [0, 0, 0]
    built = [r["built"] for _, r in results]
    assert sum(built) == NUM_SHARDS and all(b >= 1 for b in built), f"claims must split the work: {built}"
    assert any(r["manifest"] for _, r in results)
    assert shard_checksums(out) == shard_checksums(reference)
    assert validate_dataset(out) == []
    assert leftovers(out) == []


def test_a_build_with_other_arguments_is_refused_and_the_first_is_intact(reference, tmp_path):
    out = tmp_path / "shared"
    first = start(out, [1], tmp_path / "ready")
    while not (out / ".build" / "build.json").exists():
        time.sleep(0.01)
    later = start(out, [2, 3], tmp_path / "ready-later")
    (rc_first, first_result), *refused = finish(first + later)
    assert rc_first == 0 and first_result == {"built": NUM_SHARDS, "manifest": True}
    for rc, result in refused:
        assert rc == 2 and "holds a build with other arguments (v)" in result["error"]
    assert shard_checksums(out) == shard_checksums(reference)
    assert validate_dataset(out) == []


def dead_pid():
    proc = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    return int(proc.stdout)


def write_holder(path, token, host, pid, age_s=0.0):
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps({"token": token, "host": host, "pid": pid}))
    then = time.time() - age_s
    os.utime(path, (then, then))


@pytest.mark.parametrize(
    "holder, taken_over",
    [
        ("dead process on this host", True),
        ("other host, heartbeat older than the timeout", True),
        ("other host, fresh heartbeat", False),
        ("live process on this host", False),
    ],
)
def test_claims_of_gone_processes_are_taken_over_and_their_files_removed(reference, tmp_path, holder, taken_over):
    out = tmp_path / "ds"
    build_dir = out / ".build"
    build(out, num_shards=2, shard_index=1)  # leaves shards 0, 2, 4, ... to build
    token = "feedfacecafe0001"
    host, pid, age = {
        "dead process on this host": (host_identity(), dead_pid(), 0.0),
        "other host, heartbeat older than the timeout": ("elsewhere|boot|pid:[1]", 1, 120.0),
        "other host, fresh heartbeat": ("elsewhere|boot|pid:[1]", 1, 0.0),
        "live process on this host": (host_identity(), os.getppid(), 0.0),
    }[holder]
    write_holder(build_dir / "owners" / f"{token}.json", token, host, pid, age)
    write_holder(build_dir / "claims" / "train-00000.json", token, host, pid, age)
    partial = shard_temp_path(shard_paths(out, "train", 0)["frames"], token)
    marker_tmp = build_dir / f".train-00000.json.tmp-{token}"
    spill = build_dir / "spill" / f"scene000-0123456789ab.{token}.parquet"
    scratch = build_dir / f"scratch-{token}" / "detections" / "scene000.jsonl"
    for path in (partial, marker_tmp, spill, scratch):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(b"partial")

    summary = build(out, claim_timeout=60.0)
    kept = [p for p in (partial, marker_tmp, spill, scratch) if p.exists()]
    if taken_over:
        assert summary.manifest_written and shard_checksums(out) == shard_checksums(reference)
        assert kept == [] and leftovers(out) == []
    else:
        assert not summary.manifest_written and summary.pending_shards == ["train/0"]
        assert kept == [partial, marker_tmp, spill, scratch], "a live process's files are never touched"


def test_gather_merges_parts_built_apart(reference, tmp_path, capsys):
    parts = [tmp_path / f"part{i}" for i in range(3)]
    for index, part in enumerate(parts):
        assert not build(part, num_shards=3, shard_index=index).manifest_written
    out = tmp_path / "gathered"
    assert records_main(["gather", str(parts[0]), str(parts[1]), "--out", str(out)]) == 1
    assert "no part holds shard(s) train/2, train/5, train/8, train/11" in capsys.readouterr().err
    assert not (out / "manifest.json").exists()
    assert records_main(["gather", *map(str, parts), "--out", str(out)]) == 0  # completes what is there
    assert "copied 4 shard(s), kept 8" in capsys.readouterr().out
    assert shard_checksums(out) == shard_checksums(reference) and validate_dataset(out) == []

    other = tmp_path / "other"
    build(other, version=2, num_shards=3, shard_index=0)
    assert records_main(["gather", str(parts[0]), str(other), "--out", str(tmp_path / "mixed")]) == 2
    assert "holds a build with other arguments (v)" in capsys.readouterr().err
    shard = shard_paths(parts[1], "train", 1)["frames"]
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    assert records_main(["gather", *map(str, parts), "--out", str(tmp_path / "corrupt")]) == 2
    assert f"{shard}: sha256 does not match" in capsys.readouterr().err
    assert not list((tmp_path / "corrupt").rglob("*.tmp-*"))


def test_gather_refuses_a_part_of_an_older_schema_before_writing(reference, tmp_path, capsys):
    """Parts built by a usl that wrote v2 would mix versions in one dataset: refused in one line."""
    parts = [tmp_path / f"part{i}" for i in range(3)]
    for index, part in enumerate(parts):
        build(part, num_shards=3, shard_index=index)
    marker = parts[1] / ".build" / "train-00001.json"
    result = json.loads(marker.read_text())
    frames = parts[1] / result["frames"]["file"]
    result["frames"].update(write_old_file(frames, frames.with_name("v2.parquet"), "frames", 2))
    frames.with_name("v2.parquet").replace(frames)
    marker.write_text(json.dumps(result))
    out = tmp_path / "gathered"
    assert records_main(["gather", *map(str, parts), "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.count("\n") == 0 and f"{frames}: record schema v2, but this usl writes v3" in error
    assert not out.exists()
