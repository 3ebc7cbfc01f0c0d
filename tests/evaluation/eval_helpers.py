"""Tiny multi-view datasets for the evaluation tests, with ground truth rendered by pyrender.

pyrender (OpenGL) is the independent oracle: masks and depth in the records come from it, while
the evaluator renders predictions with our own z-buffer rasterizer. Every object is an ellipsoid
made from one ico-sphere, so all objects share one topology and a "perfect" predictor can return
the true meshes as ``ObjectPredictions``.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")

import numpy as np
import pyrender
import torch
import trimesh

from data_specs import load_dataset_spec
from pipelines.common import BuildOptions, ShardPlan, run_build
from pipelines.scene_shapes.render import renderer_for
from usl.evaluation.types import EvalInput
from usl.geometry import ico_sphere
from usl.geometry.cameras import look_at
from usl.model.outputs import ObjectPredictions
from usl.records import SceneRecord, encode_depth, encode_image, frame_row, make_instance, object_row

SIZE = 96
FOCAL = 110.0
SPHERE_LEVEL = 2


def ellipsoid(centre, radii, yaw: float) -> tuple[np.ndarray, np.ndarray]:
    verts, faces = ico_sphere(SPHERE_LEVEL, dtype=torch.float64)
    c, s = np.cos(yaw), np.sin(yaw)
    rot = np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]])
    return (verts.numpy() * radii) @ rot.T + np.asarray(centre), faces.numpy()


@dataclass(frozen=True)
class SceneUnit:
    scene_id: str
    seed: int
    num_views: int


def scene_objects(seed: int) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
    """Two ellipsoids (instance id, category id, world verts, faces) side by side near the origin."""
    rng = np.random.default_rng(seed)
    out = []
    for n, x in enumerate((-0.22, 0.22)):
        radii = rng.uniform(0.1, 0.2, 3)
        verts, faces = ellipsoid(
            [x + rng.uniform(-0.03, 0.03), 0.0, rng.uniform(-0.1, 0.1)], radii, rng.uniform(0, np.pi)
        )
        out.append((10 + n, 1 + (seed + n) % 3, verts, faces))
    return out


def camera_poses(num_views: int, radius: float = 1.7) -> list[np.ndarray]:
    azimuths = np.linspace(0.0, 2 * np.pi, num_views, endpoint=False) + 0.3
    return [look_at(np.array([radius * np.sin(a), 0.35, -radius * np.cos(a)]), np.zeros(3)) for a in azimuths]


def intrinsics() -> np.ndarray:
    return np.array([[FOCAL, 0, SIZE / 2], [0, FOCAL, SIZE / 2], [0, 0, 1.0]])


def render_truth(objects, pose: np.ndarray) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """pyrender: colour image, visible mask per object, planar depth (0 = background)."""
    scene = pyrender.Scene(bg_color=[0, 0, 0, 0], ambient_light=[1.0, 1.0, 1.0])
    nodes = []
    for _, _, verts, faces in objects:
        mesh = pyrender.Mesh.from_trimesh(trimesh.Trimesh(verts, faces, process=False), smooth=False)
        nodes.append(scene.add(mesh))
    K = intrinsics()
    camera = pyrender.IntrinsicsCamera(K[0, 0], K[1, 1], K[0, 2], K[1, 2], znear=0.05, zfar=20.0)
    scene.add(camera, pose=pose @ np.diag([1.0, -1.0, -1.0, 1.0]))
    renderer = renderer_for(SIZE, SIZE)  # kept: deleting one terminates every renderer's EGL display
    seg_map = {node: (n + 1, n + 1, n + 1) for n, node in enumerate(nodes)}
    seg, depth = renderer.render(scene, flags=pyrender.RenderFlags.SEG, seg_node_map=seg_map)
    color, _ = renderer.render(scene)
    return color, [seg[..., 0] == n + 1 for n in range(len(nodes))], depth


def build_scene(unit: SceneUnit) -> SceneRecord:
    objects = scene_objects(unit.seed)
    frames = []
    for view, pose in enumerate(camera_poses(unit.num_views)):
        color, masks, depth = render_truth(objects, pose)
        instances = [
            make_instance(iid, cid, m, depth) for (iid, cid, _, _), m in zip(objects, masks, strict=True) if m.any()
        ]
        frames.append(
            frame_row(
                unit.scene_id, view, encode_image(color), intrinsics(), pose, instances, SIZE, SIZE, encode_depth(depth)
            )
        )
    rows = [object_row(unit.scene_id, iid, cid, f"ellipsoid-{unit.seed}-{iid}", v, f) for iid, cid, v, f in objects]
    return SceneRecord(unit.scene_id, frames, rows)


def build_dataset(out: Path, num_scenes: int = 2, num_views: int = 4) -> Path:
    """A records folder with split "val" of ``num_scenes`` scenes and the Scene-Shapes spec (categories, baselines)."""
    spec = load_dataset_spec("scene_shapes")
    units = [SceneUnit(f"scene{s}", s, num_views) for s in range(num_scenes)]
    run_build(
        BuildOptions(out, workers=1, progress=False),
        spec,
        {"test": "eval"},
        [ShardPlan("val", 0, units)],
        build_scene,
        {"command": "tests"},
    )
    return out


class PerfectPredictor:
    """Returns the true meshes (from the objects table) as predictions: the evaluation's upper bound."""

    name = "Perfect"
    predicts_layout = True
    predicts_shape = True

    def __init__(self, uses_detections: bool = False, box_shift: float = 0.0, name: str | None = None):
        self.uses_detections = uses_detections
        self.box_shift = box_shift
        if name:
            self.name = name

    def __call__(self, inputs: list[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp in inputs:
            frame = inp.frame
            verts = torch.stack([inp.true_meshes[int(i)].verts for i in frame.instance_ids])
            faces = inp.true_meshes[int(frame.instance_ids[0])].faces
            n = len(frame.instance_ids)
            ids = torch.full((n,), -1) if self.uses_detections else frame.instance_ids.clone()
            out.append(
                ObjectPredictions(
                    boxes=frame.boxes + self.box_shift,
                    labels=frame.labels.clone(),
                    scores=torch.linspace(0.9, 0.8, n),
                    z=verts[..., 2].mean(1),
                    rho=verts[..., 2].amax(1) - verts[..., 2].amin(1),
                    verts=verts,
                    faces=faces,
                    instance_ids=ids,
                )
            )
        return out


def tiny_checkpoint(
    run_dir: Path,
    seed: int = 0,
    categories: tuple[str, ...] | None = None,
    overrides: tuple[str, ...] = (),
    iteration: int = 0,
) -> Path:
    """A randomly initialised tiny USL model saved like a training run (categories of scene_shapes by
    default), as if at ``iteration``, with config ``overrides``."""
    from usl.config import load_config, to_dict
    from usl.engine.checkpoint import write_run_checkpoint
    from usl.model.config import LayoutRange
    from usl.model.usl_model import USLModel

    spec = load_dataset_spec("scene_shapes")
    cfg = load_config("tiny", overrides)
    cfg.model.categories = categories or tuple(c["name"] for c in spec["categories"])
    cfg.model.category_ids = () if categories else tuple(int(c["id"]) for c in spec["categories"])
    cfg.model.layout_range = LayoutRange(**{k: float(v) for k, v in spec["layout"].items()})
    torch.manual_seed(seed)
    model = USLModel(cfg.model, cfg.loss)
    return write_run_checkpoint(run_dir, iteration, {"config": to_dict(cfg), "model": model.state_dict()})
