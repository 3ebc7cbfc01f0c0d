"""Mirroring a sample (``data.flip_prob``) reflects the world once: checked by projecting points
and by z-buffer renders of the reflected true meshes against the mirrored masks."""
import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from usl.config import ConfigError
from usl.data.config import DataConfig
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.data.mirror import mirror_boxes, mirror_intrinsics, mirror_pose
from usl.geometry.cameras import relative_transform, rigid_inverse, transform_points
from usl.records import RecordsDataset
from usl.render import rasterize_hard

WORLD_REFLECTION = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))


def _project(K: torch.Tensor, cam_to_world: torch.Tensor, world: torch.Tensor) -> torch.Tensor:
    cam = transform_points(world, rigid_inverse(cam_to_world))
    uvw = cam @ K.T
    return uvw[:, :2] / uvw[:, 2:]


def _random_pose(rng: np.random.Generator) -> torch.Tensor:
    pose = torch.eye(4, dtype=torch.float64)
    pose[:3, :3] = torch.from_numpy(Rotation.random(random_state=rng).as_matrix())
    pose[:3, 3] = torch.from_numpy(rng.normal(size=3))
    return pose


def test_reflected_points_land_at_w_minus_u_in_every_camera():
    rng = np.random.default_rng(0)
    width = 160
    K = torch.tensor([[150.0, 3.0, 70.5], [0.0, 140.0, 52.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    poses = [_random_pose(rng) for _ in range(3)]
    for pose in poses:
        # points in front of this camera
        cam = torch.from_numpy(rng.uniform([-1, -1, 1], [1, 1, 4], size=(20, 3)))
        world = transform_points(cam, pose)
        mirrored_pose = mirror_pose(pose)
        rotation = mirrored_pose[:3, :3]
        assert torch.allclose(rotation @ rotation.T, torch.eye(3, dtype=torch.float64), atol=1e-12)
        assert torch.linalg.det(rotation) == pytest.approx(1.0)  # a proper rigid pose
        uv = _project(K, pose, world)
        uv_mirrored = _project(mirror_intrinsics(K, width), mirrored_pose, world @ WORLD_REFLECTION.T)
        assert torch.allclose(uv_mirrored[:, 0], width - uv[:, 0], atol=1e-9)
        assert torch.allclose(uv_mirrored[:, 1], uv[:, 1], atol=1e-9)
    # the loss's relative poses become S R S
    S = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))
    relative = relative_transform(poses[0], poses[1])
    assert torch.allclose(relative_transform(mirror_pose(poses[0]), mirror_pose(poses[1])), S @ relative @ S, atol=1e-12)


def test_mirror_boxes_swaps_and_reflects_x():
    boxes = torch.tensor([[10.0, 5.0, 30.0, 25.0]])
    assert torch.equal(mirror_boxes(boxes, 100), torch.tensor([[70.0, 5.0, 90.0, 25.0]]))


def _dataset(root, flip_prob):
    records = RecordsDataset(root, "train")
    cfg = DataConfig(root=str(root), num_views=4, num_workers=0, flip_prob=flip_prob)
    dataset = MultiViewDataset(records, cfg, CategoryIndex(records.categories), seed=3, with_true_meshes=True)
    return dataset, records


def test_flipped_sample_is_the_mirror_image_of_the_same_sample(synthetic_root):
    plain, _ = _dataset(synthetic_root, 0.0)
    flipped, _ = _dataset(synthetic_root, 1.0)
    for index in (0, 9):
        a, b = plain[SampleKey(index, 1)], flipped[SampleKey(index, 1)]
        assert a.seed == b.seed and [v.view_id for v in a.views] == [v.view_id for v in b.views]
        assert torch.equal(b.frame.image, a.frame.image.flip(-1))
        assert torch.equal(b.frame.masks, a.frame.masks.flip(-1))
        assert torch.equal(b.frame.boxes, mirror_boxes(a.frame.boxes, a.frame.size[1]))
        for view_a, view_b in zip(a.views, b.views):
            assert torch.equal(view_b.masks, view_a.masks.flip(-1)) and torch.equal(view_b.present, view_a.present)
        for mesh_a, mesh_b in zip(a.true_meshes, b.true_meshes):
            assert torch.equal(mesh_b.verts[:, 0], -mesh_a.verts[:, 0]) and torch.equal(mesh_b.verts[:, 1:], mesh_a.verts[:, 1:])


def test_reflected_true_meshes_fill_the_mirrored_masks_in_every_view(synthetic_root):
    """The independent check: the reflected scene, rendered by the mirrored cameras, is what the
    mirrored masks show (in the input view from the camera-frame true meshes, elsewhere from the
    world-frame objects table reflected by M)."""
    dataset, records = _dataset(synthetic_root, 1.0)
    sample = dataset[SampleKey(2, 0)]
    scene_id, _ = dataset.items[2]
    objects = {o["instance_id"]: o for o in records.read_objects(scene_id)}
    ids = sample.frame.instance_ids[sample.object_rows].tolist()
    checked = 0
    for view in sample.views:
        height, width = view.size
        for k, instance_id in enumerate(ids):
            if not view.present[k]:
                continue
            world = torch.tensor(np.asarray(objects[instance_id]["vertices"]), dtype=torch.float64) @ WORLD_REFLECTION.T
            faces = torch.tensor(np.asarray(objects[instance_id]["faces"]), dtype=torch.int64)
            verts = transform_points(world, rigid_inverse(view.cam_to_world))
            amodal = rasterize_hard(verts, faces, torch.zeros(len(faces), dtype=torch.long), view.K.double(), height, width).masks[0]
            visible = view.masks[k]
            assert (visible & amodal).sum() / visible.sum() > 0.85
            checked += 1
    mesh = sample.true_meshes[0]
    height, width = sample.frame.size
    amodal = rasterize_hard(mesh.verts.double(), mesh.faces, torch.zeros(len(mesh.faces), dtype=torch.long),
                            sample.frame.K.double(), height, width).masks[0]
    visible = sample.frame.masks[sample.object_rows[0]]
    assert (visible & amodal).sum() / visible.sum() > 0.85
    assert checked >= 2


def test_flip_prob_outside_unit_interval_is_an_error():
    with pytest.raises(ConfigError, match="data.flip_prob"):
        DataConfig(flip_prob=1.5)
