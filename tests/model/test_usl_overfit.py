"""Training on one scene without 3D supervision makes the predicted 3D objects explain the
other views (Mask IoU against true masks there, z-buffer render, not the training renderer),
and the learned *shapes* explain them better than spheres at the same learned layout."""

from dataclasses import replace

import numpy as np
import pytest
import torch

from tests.data.synthetic_records import build_synthetic_records
from usl.cli.train import main
from usl.data import CategoryIndex, decode_frame
from usl.data.dataset import decode_target_view
from usl.engine.checkpoint import load_model
from usl.engine.train import seed_everything
from usl.evaluation.baselines import sphere_verts
from usl.geometry.cameras import relative_transform, transform_points
from usl.model.usl_model import USLModel
from usl.records import RecordsDataset
from usl.render import rasterize_hard

OVERRIDES = [
    "loss.weights.mu_2d=0",
    "loss.weights.offset_l2=0.05",
    "optim.lr=3e-3",
    "optim.max_iter=60",
    "train.batch_size=3",
    "train.cpu_threads=1",
    "data.num_views=3",
    "data.max_size=0",
    "model.shape.num_stages=1",
    "loss.mesh_points=200",
    "loss.render.resolution=32",
    "train.checkpoint_every=1000",
    "train.log_every=10",
    "data.flip_prob=0",
]


def predictions(model, root):
    """(input frame, ObjectPredictions) for every view of the scene."""
    records = RecordsDataset(root, "train")
    categories = CategoryIndex(records.categories)
    rows = records.read_scene(records.scene_ids[0])
    frames = [decode_frame(row, categories) for row in rows]
    return rows, [(frame, model.predict([frame], mode="gt_boxes")[0]) for frame in frames]


def spheres_at_layout(rows_and_predictions, level: int):
    """The same boxes, depths and extents, with the undeformed sphere as every shape."""
    rows, pairs = rows_and_predictions
    spheres = []
    for frame, pred in pairs:
        verts, faces = sphere_verts(pred.boxes, frame.K, pred.z, pred.rho, level)
        spheres.append((frame, replace(pred, verts=verts, faces=faces)))
    return rows, spheres


def other_view_iou(rows_and_predictions) -> float:
    """Mean IoU of each object's rendered prediction with its true mask in every other view."""
    rows, pairs = rows_and_predictions
    ious = []
    for position, (frame, pred) in enumerate(pairs):
        faces = pred.faces
        for other_position, other in enumerate(rows):
            if other_position == position:
                continue
            view = decode_target_view(other, frame.instance_ids)
            verts = transform_points(pred.verts.double(), relative_transform(frame.cam_to_world, view.cam_to_world))
            packed = (faces[None] + verts.shape[1] * torch.arange(len(verts))[:, None, None]).reshape(-1, 3)
            render = rasterize_hard(
                verts.reshape(-1, 3),
                packed,
                torch.arange(len(verts)).repeat_interleave(len(faces)),
                view.K.double(),
                *view.size,
            )
            for k in torch.nonzero(view.present).squeeze(1).tolist():
                inter = (render.masks[k] & view.masks[k]).sum().item()
                union = (render.masks[k] | view.masks[k]).sum().item()
                ious.append(inter / union)
    return float(np.mean(ious))


@pytest.fixture(scope="module")
def one_scene(tmp_path_factory):
    return build_synthetic_records(
        tmp_path_factory.mktemp("one_scene") / "records", num_scenes=1, num_views=6, size=48, val_scenes=0, seed=7
    )


def test_overfitting_one_scene_learns_layout_and_shape_beyond_the_sphere(one_scene, tmp_path):
    assert main(["--config", "tiny", "--out", str(tmp_path / "run"), f"data.root={one_scene}", *OVERRIDES]) == 0
    trained, config = load_model(tmp_path / "run")
    seed_everything(config.train.seed, 0)  # the trainer's own initialisation
    initial = USLModel(config.model, config.loss).eval()
    learned = predictions(trained, one_scene)
    before, after = other_view_iou(predictions(initial, one_scene)), other_view_iou(learned)
    sphere = other_view_iou(spheres_at_layout(learned, config.model.shape.ico_level))
    # a fresh layout head puts objects at z = 3.25 m, the cuboids stand ~1.7 m away: IoU ~0 before
    assert after > 0.3 and after > before + 0.2, (before, after)
    # the shape head did more than the layout: spheres at the very same z and rho explain less
    assert after > sphere + 0.1, (sphere, after)  # measured: 0.39 vs 0.14
