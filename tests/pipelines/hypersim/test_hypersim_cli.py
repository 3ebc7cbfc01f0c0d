"""The command line: options, parallel/sharded/resumed builds, and clear errors for bad input."""

import shutil

import pyarrow.parquet as pq
import pytest

from pipelines.hypersim.cli import main
from tests.pipelines.hypersim.hypersim_inputs import convert
from usl.records import RecordsDataset, decode_image, load_manifest
from usl.records.schema import file_schema_version
from usl.records.validate import validate_dataset


def all_rows(root):
    manifest = load_manifest(root)
    return {
        split: pq.read_table(root / shard["frames"]["file"]).to_pylist()
        for split, entry in manifest["splits"].items()
        for shard in entry["shards"]
    }


def test_workers_and_machines_give_the_same_records(inputs, native, tmp_path):
    parallel = convert(inputs, tmp_path / "parallel", "--image-codec", "png", "--workers", "2")
    assert all_rows(parallel) == all_rows(native)
    assert load_manifest(parallel)["skips"] == load_manifest(native)["skips"]
    sharded = tmp_path / "sharded"
    argv = inputs.argv(sharded, "--image-codec", "png", "--num-shards", "2")
    assert main(argv + ["--shard-index", "1"]) == 0
    assert not (sharded / "manifest.json").exists()  # the other machine's shard is still missing
    assert main(argv + ["--shard-index", "0"]) == 0
    assert all_rows(sharded) == all_rows(native)


def test_a_second_run_resumes(inputs, tmp_path, capsys):
    out = convert(inputs, tmp_path / "records")
    capsys.readouterr()
    convert(inputs, out)
    printed = capsys.readouterr().out
    assert "built 0 shard(s), kept 2" in printed
    assert "train: 1 trajectories, 4 views" in printed and "official exclusion" in printed


def test_filters_stride_and_stuff_exclusion(inputs, tmp_path):
    out = convert(
        inputs,
        tmp_path / "records",
        "--blacklist",
        "ai_002_001",
        "--stride",
        "2",
        "--exclude-categories",
        "stuff",
        "--resolution",
        "48x36",
    )
    assert validate_dataset(out) == []
    assert load_manifest(out)["schema_version"] == 3 and (out / "frames" / "train").is_dir()
    assert {file_schema_version(p) for p in (out / "frames").rglob("*.parquet")} == {3}  # depth an Image
    (rows,) = all_rows(out).values()
    assert [(r["scene_id"], r["view_id"]) for r in rows] == [("ai_001_001/cam_00", 0), ("ai_001_001/cam_00", 4)]
    categories = {i["category_id"] for r in rows for i in r["instances"]}
    assert categories and not categories & {1, 2, 22}
    assert rows[0]["image"]["bytes"][:2] == b"\xff\xd8"  # JPEG by default
    assert decode_image(rows[0]["image"]).shape == (36, 48, 3)
    only_val = convert(inputs, tmp_path / "val", "--splits", "val", "--cameras", "cam_00")
    assert RecordsDataset(only_val, "val").scene_ids == ["ai_002_001/cam_00"]
    assert set(load_manifest(only_val)["splits"]) == {"val"}


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--resolution", "64by48"], "--resolution '64by48'"),
        (["--exclude-categories", "sofas"], "'sofas' is not a Hypersim category"),
        (["--blacklist", "ai_1_1"], "blacklist entry 'ai_1_1'"),
        (["--splits", "nosuchsplit"], "nothing to convert"),
    ],
)
def test_bad_arguments_are_one_line_errors(inputs, tmp_path, capsys, extra, message):
    assert main(inputs.argv(tmp_path / "out", *extra)) == 2
    assert message in capsys.readouterr().err


def test_scenes_missing_from_the_csvs_are_errors_naming_the_csv(inputs, tmp_path, capsys):
    camera_csv = tmp_path / "cameras.csv"
    lines = inputs.camera_csv.read_text().splitlines()
    camera_csv.write_text("\n".join(line for line in lines if not line.startswith("ai_002_001")) + "\n")
    argv = inputs.argv(tmp_path / "out")
    argv[argv.index("--camera-csv") + 1] = str(camera_csv)
    assert main(argv) == 2
    assert f"{camera_csv}: no camera parameters for scene ai_002_001" in capsys.readouterr().err
    split_csv = tmp_path / "split.csv"
    split_csv.write_text(
        "\n".join(line for line in inputs.split_csv.read_text().splitlines() if not line.startswith("ai_002_001"))
        + "\n"
    )
    argv = inputs.argv(tmp_path / "out2")
    argv[argv.index("--split-csv") + 1] = str(split_csv)
    assert main(argv) == 2
    assert f"{split_csv}: scene ai_002_001" in capsys.readouterr().err


def test_missing_pose_file_is_a_recorded_skip_or_stops_the_build_naming_it(inputs, tmp_path, capsys):
    scene = shutil.copytree(inputs.scenes_root / "ai_002_001", tmp_path / "ai_002_001")
    (scene / "_detail" / "cam_00" / "camera_keyframe_positions.hdf5").unlink()
    argv = inputs.argv(tmp_path / "out")
    argv[0] = str(scene)
    message = "ai_002_001/_detail/cam_00/camera_keyframe_positions.hdf5: file not found"
    assert main(argv + ["--no-skip-bad-scenes"]) == 2
    assert message in capsys.readouterr().err
    assert not (tmp_path / "out" / "manifest.json").exists()
    # By default the scene becomes a skip; here it was the only one with views, so the build fails.
    assert main(argv) == 2
    assert "every scene built so far failed" in capsys.readouterr().err
