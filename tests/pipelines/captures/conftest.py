"""A rendered capture (table and chair along an arc, noise-textured, with depth and detections), written
as transforms.json, as a COLMAP text model and as a COLMAP binary model. Built once per test run."""

from __future__ import annotations

import shutil
from types import SimpleNamespace

import pytest

from tests.pipelines.captures.synthetic_capture import (
    render_capture,
    write_colmap_text,
    write_detections,
    write_transforms,
)

UNIT = 0.37  # metres per unit of the COLMAP models' world: poses are not metric there


@pytest.fixture(scope="session")
def capture(tmp_path_factory: pytest.TempPathFactory) -> SimpleNamespace:
    root = tmp_path_factory.mktemp("captures")
    truth = render_capture(num_frames=24, width=160, height=120)
    write_transforms(truth, root / "nerfstudio")
    write_detections(truth, root / "nerfstudio")
    write_colmap_text(truth, root / "colmap_text", UNIT)
    write_detections(truth, root / "colmap_text")
    return SimpleNamespace(root=root, truth=truth)


@pytest.fixture(scope="session")
def colmap_binary(capture: SimpleNamespace) -> SimpleNamespace:
    """The COLMAP text capture with its model in binary, where nerfstudio's ns-process-data puts it."""
    pycolmap = pytest.importorskip("pycolmap")
    root = capture.root
    binary = root / "colmap_binary"
    shutil.copytree(root / "colmap_text", binary)
    shutil.rmtree(binary / "sparse")
    (binary / "colmap" / "sparse" / "0").mkdir(parents=True)
    model = pycolmap.Reconstruction()
    model.read_text(str(root / "colmap_text" / "sparse" / "0"))
    model.write_binary(str(binary / "colmap" / "sparse" / "0"))
    return capture
