"""Every bad input of issue 12 gives one clear line naming the file (and scene, view), loses
nothing, and no command that did not do its work reports success. Table-driven: one row per input."""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pytest

from pipelines.common import BuildOptions, ShardPlan, run_build
from pipelines.hypersim.metadata import read_camera_csv, read_split_csv
from pipelines.scene_shapes.cli import main as scene_shapes_main
from tests.records.fake_scenes import SPEC, build_fake_scene, fake_frames
from usl.cli.evaluate import main as eval_main
from usl.cli.records import main as records_main
from usl.data import CategoryIndex, MultiViewDataset
from usl.data.config import DataConfig
from usl.errors import UslError
from usl.records import RecordsDataset, SceneRecord
from usl.records.shards import shard_paths

SHARD = shard_paths(Path(), "train", 0)["frames"].as_posix()  # where the layout puts train shard 0


def broken_scene(unit):
    """Scene ``s1`` has an empty image in view 1 and a box outside the image in view 2; scene
    ``rle`` has a corrupt mask in view 0; the others are good."""
    scene_id, seed, views = unit
    rows = list(fake_frames(scene_id, seed, views))
    if scene_id == "s1":
        rows[1]["image"]["bytes"] = b""
        rows[2]["instances"][0]["box_xyxy"] = [0.0, 0.0, 99.0, 5.0]
    if scene_id == "rle":
        rows[0]["instances"][0]["mask"]["counts"] = "garbage!!"
    return SceneRecord(scene_id, rows, build_fake_scene(unit).objects)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("bad") / "ds"
    plans = [
        ShardPlan("train", 0, [("rle", 0, 2), ("s1", 1, 3), ("s2", 2, 2)]),
        ShardPlan("val", 0, [("empty", 3, 0)]),
    ]  # val: a split whose only scene was skipped
    spec = {**SPEC, "baselines": {"random_depth": {"z": [1.4, 2.0], "rho": [0.1, 1.0]}}}
    run_build(BuildOptions(root, progress=False), spec, {}, plans, broken_scene, {"command": "test"})
    return root


def edit_manifest(root: Path, edit: Callable[[dict], object]) -> None:
    manifest = json.loads((root / "manifest.json").read_text())
    result = edit(manifest)
    (root / "manifest.json").write_text(json.dumps(manifest if result is None else result))


def set_file(path: str) -> Callable[[dict], None]:
    def edit(manifest: dict) -> None:
        manifest["splits"]["train"]["shards"][0]["frames"]["file"] = path

    return edit


def flip_bytes(root: Path) -> None:
    """Flip bytes inside the image data of the train shard, keeping its size."""
    shard = root / SHARD
    data = bytearray(shard.read_bytes())
    for k in range(len(data) // 3, len(data) // 3 + 64):
        data[k] ^= 0xFF
    shard.write_bytes(bytes(data))


def read_only_folder(tmp_path: Path) -> Path:
    if os.geteuid() == 0:  # root ignores permission bits; /sys refuses new entries even to root
        return Path("/sys/usl-test-output")
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    return folder / "ds"


@dataclass
class Case:
    name: str
    damage: Callable[[Path, Path], object]  # (dataset copy, tmp_path) -> arguments for run
    run: Callable[..., object]  # returns an exit code or raises UslError
    expect: str  # in the one-line error
    code: int = 2


def cli(main):
    return lambda *argv: main([str(a) for a in argv])


def reader(root, split="train", verify="size"):
    ds = RecordsDataset(root, split, verify=verify)
    return [ds.read_scene(s) for s in ds.scene_ids]


def train_sample(root, index=0):
    records = RecordsDataset(root, "train")
    return MultiViewDataset(records, DataConfig(num_views=2, flip_prob=0.0), CategoryIndex(records.categories))[index]


def fake_build(out):
    return run_build(
        BuildOptions(out, progress=False), SPEC, {}, [ShardPlan("train", 0, [("a", 0, 1)])], build_fake_scene, {}
    )


CASES = [
    Case(
        "manifest is a JSON list",
        lambda r, t: (edit_manifest(r, lambda m: [m]), ("validate", r))[1],
        cli(records_main),
        "expected a JSON object, found a list",
        code=1,
    ),
    Case(
        "manifest is a JSON list (info)",
        lambda r, t: (edit_manifest(r, lambda m: [m]), ("info", r))[1],
        cli(records_main),
        "expected a JSON object, found a list",
    ),
    Case(
        "manifest without splits",
        lambda r, t: (edit_manifest(r, lambda m: m.pop("splits") and None), (r,))[1],
        reader,
        "no 'splits' object",
    ),
    Case(
        "shard path outside the folder (validate)",
        lambda r, t: (edit_manifest(r, set_file("../outside/x.parquet")), ("validate", r))[1],
        cli(records_main),
        "'../outside/x.parquet' points outside the dataset folder",
        code=1,
    ),
    Case(
        "shard path outside the folder (reader)",
        lambda r, t: (edit_manifest(r, set_file("../outside/x.parquet")), (r,))[1],
        reader,
        "points outside the dataset folder",
    ),
    Case(
        "absolute shard path (info)",
        lambda r, t: (edit_manifest(r, set_file(str(r / SHARD))), ("info", r))[1],
        cli(records_main),
        "points outside the dataset folder",
    ),
    Case(
        "--out is a file",
        lambda r, t: ((t / "file").write_text("x"), (t / "file",))[1],
        fake_build,
        "--out is a file, not a folder",
    ),
    Case("read-only output folder", lambda r, t: (read_only_folder(t),), fake_build, "cannot write"),
    Case(
        "truncated shard (info)",
        lambda r, t: ((r / SHARD).write_bytes((r / SHARD).read_bytes()[:-100]), ("info", r))[1],
        cli(records_main),
        "(truncated or replaced)",
    ),
    Case(
        "truncated shard (reader)",
        lambda r, t: ((r / SHARD).write_bytes((r / SHARD).read_bytes()[:-100]), (r,))[1],
        reader,
        f"{SHARD}: size",
    ),
    Case("flipped bytes (reader, page checksums)", lambda r, t: (flip_bytes(r), (r,))[1], reader, f"{SHARD}: scene"),
    Case(
        "flipped bytes (data.verify=sha256)",
        lambda r, t: (flip_bytes(r), (r, "train", "sha256"))[1],
        reader,
        f"{SHARD}: sha256 does not match",
    ),
    Case(
        "corrupt RLE (training sample)",
        lambda r, t: (r,),
        train_sample,
        f"{SHARD}: scene 'rle' view 0: mask RLE does not decode",
    ),
    Case(
        "contact sheet cannot be written",
        lambda r, t: ((t / "f").write_text("x"), ("info", r, "--split", "val", "--sheet", t / "f" / "sheet.png"))[1],
        cli(records_main),
        "cannot write the contact sheet",
    ),
    Case(
        "--ray-address without --executor ray",
        lambda r, t: ("--out", t / "ss", "--ray-address", "auto"),
        cli(scene_shapes_main),
        "--ray-address needs --executor ray",
    ),
    Case(
        "usl-eval on an empty split",
        lambda r, t: (r, "--split", "val", "--rows", "random", "--out", t / "eval", "--quiet"),
        cli(eval_main),
        "split 'val' has no scenes to evaluate",
    ),
]


@pytest.mark.parametrize("case", CASES, ids=[c.name for c in CASES])
def test_bad_input_gives_one_line_naming_it(case, dataset, tmp_path, capsys):
    root = tmp_path / "copy"
    shutil.copytree(dataset, root)
    args = case.damage(root, tmp_path)
    try:
        code = case.run(*args)
        captured = capsys.readouterr()
        message = (captured.err + captured.out).strip()
    except UslError as exc:
        code, message = 2, str(exc)
    assert code == case.code, message
    line = [m for m in message.splitlines() if case.expect in m]
    assert line, f"{case.expect!r} not in {message!r}"
    assert "Traceback" not in message and "\n" not in str(line[0])


def test_validate_reports_an_empty_image_and_keeps_checking_the_shard(dataset, capsys):
    assert records_main(["validate", str(dataset)]) == 1
    problems = capsys.readouterr().out.splitlines()
    assert any(f"{SHARD}: scene 's1' view 1: image bytes are empty" in p for p in problems)
    assert any(f"{SHARD}: scene 's1' view 2: instance 7: box_xyxy" in p for p in problems), "rows after it are checked"
    assert any("scene 'rle' view 0: instance 7: mask RLE does not decode" in p for p in problems)


@pytest.mark.parametrize(
    "content, expect",
    [
        (
            "scene_name,camera_name,frame_id,included_in_public_release,exclude_reason,split_partition_name\n"
            "ai_001_001,cam_00,0,True\n",
            ":2: the row has fewer fields than the header",
        ),
        (
            "scene_name,camera_name,frame_id,included_in_public_release,exclude_reason,split_partition_name\n"
            "ai_001_001,cam_00,0,True,,train,extra\n",
            ":2: the row has more fields than the header",
        ),
    ],
)
def test_hypersim_split_csv_with_a_bad_row(tmp_path, content, expect):
    path = tmp_path / "split.csv"
    path.write_text(content)
    with pytest.raises(UslError, match=expect):
        read_split_csv(path)


def test_hypersim_csv_that_is_not_utf8(tmp_path):
    path = tmp_path / "cameras.csv"
    path.write_bytes(b"scene_name,settings_output_img_width\n\xff\xfe\x00bad\n")
    with pytest.raises(UslError, match="cameras.csv: not UTF-8 text"):
        read_camera_csv(path)
