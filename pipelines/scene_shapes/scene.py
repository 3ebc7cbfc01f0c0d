"""Building one scene record: load its models, render all views, derive instances, emit rows.

``build_scene`` runs in worker processes; everything it needs travels in its ``SceneUnit``, and
all randomness comes from the unit (layout sampled by the planner, appearance seed), so the
output does not depend on which worker builds it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from usl.errors import UslError
from usl.geometry.cameras import transform_points
from usl.records import SceneRecord, Skip, encode_depth, encode_image, frame_row, make_instance, object_row

from .layout import RigConfig, SceneLayout
from .mesh_root import MeshNormalisation, load_mesh_model
from .render import PlacedModel, render_scene
from .shapes import ModelRef, ShapeModel, generate_procedural


@dataclass(frozen=True)
class SceneConfig:
    """Settings shared by every scene of a build."""

    rig: RigConfig
    category_ids: tuple[tuple[str, int], ...]  # category name -> id of data_specs/scene_shapes.yaml
    background: str = "floor"
    image_codec: str = "png"
    mesh_normalisation: MeshNormalisation | None = None  # None: procedural models
    skip_bad_meshes: bool = False


@dataclass(frozen=True)
class SceneUnit:
    scene_id: str
    layout: SceneLayout
    appearance_seed: int
    config: SceneConfig


def load_model(ref: ModelRef, normalisation: MeshNormalisation | None) -> ShapeModel:
    if ref.path is None:
        return generate_procedural(ref.source_id)
    if normalisation is None:
        raise UslError(f"{ref.source_id}: a mesh-file model needs mesh normalisation settings")
    return load_mesh_model(ref, normalisation)


def transform_vertices(vertices: np.ndarray, transform: np.ndarray) -> np.ndarray:
    return transform_points(torch.tensor(vertices), torch.as_tensor(transform)).numpy()  # copy: models are read-only


def build_scene(unit: SceneUnit) -> SceneRecord:
    """Render one scene into frame rows (image, depth, instances per view) and object rows."""
    config, layout = unit.config, unit.layout
    category_ids = dict(config.category_ids)
    models = []
    for placement in layout.objects:
        try:
            models.append(load_model(placement.model, config.mesh_normalisation))
        except UslError as exc:
            if not config.skip_bad_meshes:
                raise
            # The scene is left out and the manifest says which mesh and why.
            return SceneRecord(
                unit.scene_id, [], skips=[Skip(f"scene left out, unreadable mesh: {exc}", placement.model.source_id)]
            )
    transforms = [p.world_from_object() for p in layout.objects]
    views = render_scene(
        [PlacedModel(m, t) for m, t in zip(models, transforms, strict=True)],
        layout.K,
        list(layout.cam_to_world),
        config.rig.resolution,
        config.background,
        np.random.default_rng(unit.appearance_seed),
    )
    size = config.rig.resolution
    frames = []
    for view_id, (view, pose) in enumerate(zip(views, layout.cam_to_world, strict=True)):
        instances = []
        for index, placement in enumerate(layout.objects, start=1):
            mask = view.instance_index == index
            if mask.any():  # wholly occluded objects are absent from this view
                instances.append(
                    make_instance(placement.instance_id, category_ids[placement.model.category], mask, view.depth)
                )
        frames.append(
            frame_row(
                unit.scene_id,
                view_id,
                encode_image(view.rgb, config.image_codec),
                layout.K,
                pose,
                instances,
                size,
                size,
                encode_depth(view.depth),
            )
        )
    objects = [
        object_row(
            unit.scene_id,
            p.instance_id,
            category_ids[p.model.category],
            p.model.source_id,
            transform_vertices(m.vertices, t),
            m.faces,
        )
        for p, m, t in zip(layout.objects, models, transforms, strict=True)
    ]
    return SceneRecord(unit.scene_id, frames, objects)
