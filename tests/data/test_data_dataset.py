"""Multi-view samples from records, checked against the records themselves and a z-buffer render."""
import numpy as np
import torch

from usl.data.config import DataConfig
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.data.transforms import resize_frame
from usl.geometry.cameras import relative_transform, transform_points
from usl.records import RecordsDataset, decode_mask
from usl.render import rasterize_hard


def _dataset(root, **overrides):
    records = RecordsDataset(root, "train")
    # unmirrored, so each sample can be checked against the records as stored
    cfg = DataConfig(root=str(root), num_views=4, num_workers=0, **{"flip_prob": 0.0, **overrides})
    return MultiViewDataset(records, cfg, CategoryIndex(records.categories), seed=3), records


def test_sample_views_hold_the_records_masks_of_the_input_objects(synthetic_root):
    dataset, records = _dataset(synthetic_root)
    assert len(dataset) == sum(records.num_views(s) for s in records.scene_ids)
    for index in (0, 7, 15):
        sample = dataset[SampleKey(index, 0)]
        scene_id, position = dataset.items[index]
        rows = records.read_scene(scene_id)
        ids = sample.frame.instance_ids[sample.object_rows].tolist()
        assert sample.views[0].view_id == sample.frame.view_id == rows[position]["view_id"]
        assert sample.views[0].present.all()
        assert 2 <= len(sample.views) <= 4 and len({v.view_id for v in sample.views}) == len(sample.views)
        for view in sample.views:
            row = next(r for r in rows if r["view_id"] == view.view_id)
            assert torch.allclose(view.cam_to_world, torch.tensor(row["cam_to_world"], dtype=torch.float64).view(4, 4))
            by_id = {i["instance_id"]: decode_mask(i["mask"]) for i in row["instances"]}
            for k, instance_id in enumerate(ids):
                assert bool(view.present[k]) == (instance_id in by_id)
                expected = by_id.get(instance_id, np.zeros(view.size, dtype=bool))
                assert np.array_equal(view.masks[k].numpy(), expected)


def test_same_key_same_sample_and_object_subset(synthetic_root):
    dataset, _ = _dataset(synthetic_root, max_objects=1)
    a, b = dataset[SampleKey(5, 2)], dataset[SampleKey(5, 2)]
    assert a.seed == b.seed and [v.view_id for v in a.views] == [v.view_id for v in b.views]
    assert len(a.object_rows) == 1 and torch.equal(a.object_rows, b.object_rows)
    seeds = {dataset[SampleKey(5, epoch)].seed for epoch in range(4)}
    assert len(seeds) == 4  # each epoch draws anew


def test_resized_views_agree_with_the_true_meshes(synthetic_root):
    """Masks and K resized together: the true mesh rendered with the resized K fills the resized mask."""
    dataset, records = _dataset(synthetic_root, max_size=40)
    sample = dataset[SampleKey(2, 0)]
    scene_id, _ = dataset.items[2]
    meshes = {o["instance_id"]: o for o in records.read_objects(scene_id)}
    ids = sample.frame.instance_ids[sample.object_rows].tolist()
    assert sample.frame.image.shape[-2:] == (40, 40)
    for view in sample.views:
        assert view.size == (40, 40)
        for k, instance_id in enumerate(ids):
            if not view.present[k]:
                continue
            obj = meshes[instance_id]
            world = torch.tensor(np.asarray(obj["vertices"]), dtype=torch.float64)
            verts = transform_points(world, torch.linalg.inv(view.cam_to_world))
            faces = torch.tensor(np.asarray(obj["faces"]), dtype=torch.int64)
            amodal = rasterize_hard(verts, faces, torch.zeros(len(faces), dtype=torch.long), view.K.double(), 40, 40).masks[0]
            visible = view.masks[k]
            # the visible mask lies inside the object's own (amodal) silhouette, up to resampling
            inside = (visible & amodal).sum() / visible.sum()
            assert inside > 0.85


def test_resize_frame_scales_boxes_and_K_consistently(synthetic_root):
    dataset, _ = _dataset(synthetic_root)
    frame = dataset[SampleKey(0, 0)].frame
    small = resize_frame(frame, 32)
    assert torch.allclose(small.boxes, frame.boxes / 2)
    assert torch.allclose(small.K[:2], frame.K[:2] / 2) and torch.allclose(small.K[2], frame.K[2])
    point = torch.tensor([[0.1, -0.2, 2.0]])
    uv_big = (frame.K @ point.T).T
    uv_small = (small.K @ point.T).T
    assert torch.allclose(uv_small[:, :2] / uv_small[:, 2:], uv_big[:, :2] / uv_big[:, 2:] / 2, atol=1e-5)


def test_relative_transform_maps_input_camera_to_other_views(synthetic_root):
    """R_{1->j} takes a true mesh from the input camera frame to where view j's K sees its mask."""
    dataset, records = _dataset(synthetic_root)
    sample = dataset[SampleKey(1, 0)]
    scene_id, _ = dataset.items[1]
    obj = records.read_objects(scene_id)[0]
    k = sample.frame.instance_ids[sample.object_rows].tolist().index(obj["instance_id"])
    world = torch.tensor(np.asarray(obj["vertices"]), dtype=torch.float64)
    in_input = transform_points(world, torch.linalg.inv(sample.views[0].cam_to_world))
    faces = torch.tensor(np.asarray(obj["faces"]), dtype=torch.int64)
    for view in sample.views[1:]:
        if not view.present[k]:
            continue
        verts = transform_points(in_input, relative_transform(sample.views[0].cam_to_world, view.cam_to_world))
        amodal = rasterize_hard(verts, faces, torch.zeros(len(faces), dtype=torch.long), view.K.double(), *view.size).masks[0]
        assert (amodal & view.masks[k]).sum() == view.masks[k].sum()  # exact: same renderer, same pose
