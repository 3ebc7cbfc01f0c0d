"""The rendered capture shares the process's renderers: rendering it must leave every other
renderer of the process working (deleting a pyrender EGL renderer terminates the process-wide EGL
display, and every test that rendered later in the same pytest worker failed in ``eglMakeCurrent``)."""

from __future__ import annotations

import numpy as np
import pyrender
import trimesh

from pipelines.scene_shapes.render import renderer_for
from tests.pipelines.captures.synthetic_capture import render_capture


def _box_coverage(size: int) -> int:
    scene = pyrender.Scene()
    scene.add(pyrender.Mesh.from_trimesh(trimesh.creation.box((1.0, 1.0, 1.0))))
    scene.add(
        pyrender.PerspectiveCamera(yfov=1.0), pose=np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 3.0], [0, 0, 0, 1]])
    )
    depth = renderer_for(size, size).render(scene, flags=pyrender.RenderFlags.DEPTH_ONLY)
    return int((depth > 0).sum())


def test_rendering_a_capture_leaves_other_renderers_working():
    before = _box_coverage(33)
    capture = render_capture(num_frames=2, width=48, height=36)
    assert len(capture.images) == 2 and capture.masks[0]["table"].any()
    assert _box_coverage(33) == before > 0
