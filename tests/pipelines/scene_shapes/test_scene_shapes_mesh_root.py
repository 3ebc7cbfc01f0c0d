"""--mesh-root: a ShapeNet-like tree of OBJ/PLY/OFF files written by trimesh, category maps, bad files."""

import numpy as np
import pytest
import trimesh

from pipelines.scene_shapes.cli import main
from pipelines.scene_shapes.mesh_root import (
    DEFAULT_DIAGONAL_M,
    MeshNormalisation,
    discover_models,
    load_category_map,
    load_mesh_model,
)
from pipelines.scene_shapes.shapes import generate_procedural, procedural_source_id
from usl.errors import UslError
from usl.records import RecordsDataset, load_manifest

# Synset ids as in ShapeNet; 03001627 is a valid octal literal for YAML 1.1, a classic pitfall.
SYNSETS = {"03001627": "chair", "04256520": "sofa", "04379243": "table"}
FAMILY = {"chair": "four_legged", "sofa": "armless", "table": "coffee"}
Z_UP = np.array([[1.0, 0, 0, 0], [0, 0, -1.0, 0], [0, 1.0, 0, 0], [0, 0, 0, 1.0]])  # +Y (ours) -> +Z


def write_tree(root, z_up=False):
    """Three models per category, one file format each, in ShapeNet-like and flat layouts."""
    layouts = ["{s}/{m}/models/model_normalized.obj", "{s}/{m}/model.ply", "{s}/{m}.off"]
    for synset, category in SYNSETS.items():
        for k, layout in enumerate(layouts):
            model = generate_procedural(procedural_source_id(category, FAMILY[category], k))
            mesh = trimesh.Trimesh(model.vertices * 0.37, model.faces)  # arbitrary source units
            if z_up:
                mesh.apply_transform(Z_UP)
            path = root / layout.format(s=synset, m=f"model{k}")
            path.parent.mkdir(parents=True, exist_ok=True)
            mesh.export(path)
    (root / "02691156").mkdir()  # a category the map leaves out
    trimesh.creation.box().export(root / "02691156" / "plane.obj")
    (root / "taxonomy.json").write_text("{}")


def write_map(path, text):
    path.write_text(text)
    return path


@pytest.fixture
def tree(tmp_path):
    root = tmp_path / "shapenet"
    write_tree(root)
    category_map = write_map(tmp_path / "map.yaml", "".join(f"{s}: {c}\n" for s, c in SYNSETS.items()))
    return root, category_map


def test_discovers_models_with_relative_source_ids(tree):
    root, map_path = tree
    refs, unmapped = discover_models(root, load_category_map(map_path))
    assert unmapped == ["02691156"]
    assert len(refs) == 9
    assert {r.category for r in refs} == {"chair", "sofa", "table"}
    assert "03001627/model0/models/model_normalized.obj" in {r.source_id for r in refs}
    assert {r.source_id.rsplit(".", 1)[1] for r in refs} == {"obj", "ply", "off"}


@pytest.mark.parametrize("z_up", [False, True])
def test_normalises_scale_and_up_axis(tmp_path, z_up):
    root = tmp_path / "meshes"
    write_tree(root, z_up=z_up)
    category_map = load_category_map(
        write_map(tmp_path / "map.json", '{"03001627": "chair", "04256520": "sofa", "04379243": "table"}')
    )
    refs, _ = discover_models(root, category_map)
    normalisation = MeshNormalisation(up_axis="+z" if z_up else "+y")
    for ref in refs:
        model = load_mesh_model(ref, normalisation)
        low, high = model.vertices.min(axis=0), model.vertices.max(axis=0)
        assert np.linalg.norm(high - low) == pytest.approx(DEFAULT_DIAGONAL_M[ref.category])
        assert low[1] == pytest.approx(0.0, abs=1e-9) and low[0] + high[0] == pytest.approx(0.0, abs=1e-9)
        index = int(ref.source_id.split("/")[1][len("model") :].split(".")[0])
        original = generate_procedural(procedural_source_id(ref.category, FAMILY[ref.category], index))
        ratio = original.extents / np.linalg.norm(original.extents)
        np.testing.assert_allclose(model.extents / np.linalg.norm(model.extents), ratio, atol=1e-6)  # upright again


def test_category_map_errors(tree, tmp_path):
    root, _ = tree
    with pytest.raises(UslError, match="unknown category 'bed'"):
        load_category_map(write_map(tmp_path / "bad.yaml", "03001627: bed\n"))
    with pytest.raises(UslError, match="do not exist"):
        discover_models(root, load_category_map(write_map(tmp_path / "missing.yaml", "99999999: chair\n")))
    nested = load_category_map(
        write_map(tmp_path / "nested.yaml", "categories: {03001627: chair}\ntarget_diagonal_m: {chair: 0.9}\n")
    )
    assert nested.folders == {"03001627": "chair"} and nested.diagonals["chair"] == 0.9


def test_empty_and_corrupt_files_are_named(tree):
    root, map_path = tree
    empty = root / "03001627" / "model0" / "models" / "model_normalized.obj"
    empty.write_text("")
    with pytest.raises(UslError, match="model_normalized.obj: empty mesh file"):
        discover_models(root, load_category_map(map_path))
    empty.write_text("this is not a mesh\n")
    refs, _ = discover_models(root, load_category_map(map_path))
    bad = next(r for r in refs if r.path == str(empty))
    with pytest.raises(UslError, match=f"{empty}: "):
        load_mesh_model(bad, MeshNormalisation())


BUILD = ["--num-scenes", "6", "--resolution", "48", "--azimuths", "2", "--heights", "1", "--quiet"]


def test_build_from_mesh_root(tree, tmp_path):
    root, map_path = tree
    out = tmp_path / "out"
    assert main(["--out", str(out), "--mesh-root", str(root), "--category-map", str(map_path), *BUILD]) == 0
    source_ids = set()
    for split in ("train", "val", "test"):
        data = RecordsDataset(out, split)
        for scene_id in data.scene_ids:
            for row in data.read_objects(scene_id):
                assert (root / row["source_id"]).is_file()
                source_ids.add(row["source_id"])
    assert source_ids and all(s.split("/")[0] in SYNSETS for s in source_ids)


def test_corrupt_meshes_stop_the_build_or_are_recorded_skips(tree, tmp_path, capsys):
    root, map_path = tree
    for table in (root / "04379243").rglob("*.*"):
        table.write_text("not a mesh at all\n")
    args = ["--mesh-root", str(root), "--category-map", str(map_path), *BUILD, "--num-scenes", "10"]
    assert main(["--out", str(tmp_path / "strict"), *args]) == 2
    assert "04379243" in capsys.readouterr().err
    out = tmp_path / "lenient"
    assert main(["--out", str(out), *args, "--skip-bad-meshes"]) == 0
    manifest = load_manifest(out)
    assert manifest["num_skipped"] >= 1
    assert all(s["path"].startswith("04379243/") for s in manifest["skips"])
    kept = sum(e["num_scenes"] for e in manifest["splits"].values())
    assert kept + manifest["num_skipped"] == 10
    for split in manifest["splits"]:
        data = RecordsDataset(out, split)
        for scene_id in data.scene_ids:
            assert all(not r["source_id"].startswith("04379243/") for r in data.read_objects(scene_id))
