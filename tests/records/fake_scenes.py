"""A tiny synthetic dataset builder for records tests: deterministic scenes of discs on noise."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import numpy as np

from pipelines.common import frame_sink
from usl.records import SceneRecord, Skip, encode_depth, encode_image, frame_row, make_instance, object_row

SPEC = {
    "name": "fake",
    "categories": [{"id": 1, "name": "disc"}, {"id": 2, "name": "square"}],
    "layout": {"z0": 1.0, "z1": 3.0, "rho0": 0.1, "rho1": 1.0},
}
SIZE = 32


def fake_frames(scene_id: str, seed: int, num_views: int) -> Iterator[dict[str, Any]]:
    """View v shows two shapes moving with v, on noise drawn from ``seed``; scene seed 1 has no depth in view 2."""
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:SIZE, 0:SIZE] + 0.5
    for view in range(num_views):
        image = rng.integers(0, 255, (SIZE, SIZE, 3), dtype=np.uint8)
        depth = np.full((SIZE, SIZE), 2.0 + 0.01 * view)
        depth[0, :6] = [np.nan, 0.001, 32.767, 32.768, 40.0, 65.535]  # unknown, and the ends of the 16-bit range
        cx, cy = 8 + view % 8, 10 + (seed % 5)
        disc = (xx - cx) ** 2 + (yy - cy) ** 2 < 25
        square = (np.abs(xx - 22) < 4) & (np.abs(yy - 20 - view % 3) < 4)
        instances = [make_instance(7, 1, disc, depth), make_instance(9, 2, square, depth * 1.5)]
        K = np.array([[30.0, 0, SIZE / 2], [0, 30.0, SIZE / 2], [0, 0, 1]])
        pose = np.eye(4)
        pose[0, 3] = 0.1 * view
        depth_png = None if (seed, view) == (1, 2) else encode_depth(depth)  # one view without depth
        yield frame_row(scene_id, view, encode_image(image), K, pose, instances, SIZE, SIZE, depth_png)


def fake_objects(scene_id: str, seed: int) -> list[dict[str, Any]]:
    tri = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float32) * (1 + seed % 3)
    return [
        object_row(scene_id, 7, 1, f"disc-{seed}", tri, np.array([[0, 1, 2]])),
        object_row(scene_id, 9, 2, f"square-{seed}", tri + 1, np.array([[0, 2, 1]])),
    ]


def build_fake_scene(unit: tuple[str, int, int]) -> SceneRecord:
    """Scene ``unit = (scene_id, seed, num_views)`` with all its rows in memory."""
    scene_id, seed, num_views = unit
    if num_views == 0:
        return SceneRecord(scene_id, [], skips=[Skip("no usable views", f"{scene_id}.fake")])
    return SceneRecord(scene_id, list(fake_frames(scene_id, seed, num_views)), fake_objects(scene_id, seed))


def build_streamed_fake_scene(unit: tuple[str, int, int]) -> SceneRecord:
    """The same scene through ``frame_sink``: rows past the first row group go to a spill file."""
    scene_id, seed, num_views = unit
    with frame_sink(scene_id) as sink:
        for row in fake_frames(scene_id, seed, num_views):
            sink.add(row)
        if num_views == 0:
            return sink.finish(skips=[Skip("no usable views", f"{scene_id}.fake")])
        return sink.finish(fake_objects(scene_id, seed))
