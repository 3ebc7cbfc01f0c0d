"""The ``--formats html`` page in a real browser: headless Chromium renders it, and the objects show
where K projects them, lit, in front of the input image (Debian: ``apt-get install chromium``)."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from usl.data.frames import CategoryIndex
from usl.evaluation.baselines import sphere_verts
from usl.inference.gltf_scene import prediction_scene, scene_glb
from usl.inference.gltf_viewer import viewer_html
from usl.model.outputs import ObjectPredictions

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None, reason="headless Chromium is not installed (Debian: apt-get install -y chromium)"
)
IMAGE_RGB = (60, 90, 140)
CATEGORIES = CategoryIndex([{"id": 1, "name": "chair"}, {"id": 2, "name": "sofa"}, {"id": 3, "name": "table"}])
PAGE_BACKGROUND = (32, 32, 32)
SCALE = 2  # screenshot pixels per image pixel


def screenshot(page: Path, width: int, height: int) -> np.ndarray:
    """RGB screenshot of ``page`` by headless Chromium with software WebGL (SwiftShader)."""
    shot = page.with_suffix(".png")
    command = [
        CHROMIUM,
        "--headless",
        "--no-sandbox",  # root in containers
        "--disable-gpu",
        "--use-angle=swiftshader",
        "--enable-unsafe-swiftshader",
        "--hide-scrollbars",
        f"--window-size={width},{height}",
        "--virtual-time-budget=15000",  # run the page's scripts until the scene is drawn
        f"--screenshot={shot}",
        page.as_uri(),
    ]
    log = page.with_suffix(".log")
    with log.open("w") as stderr:  # not a pipe: Chromium's helper processes would hold it open
        done = subprocess.run(command, stdout=subprocess.DEVNULL, stderr=stderr, timeout=120)
    assert done.returncode == 0 and shot.is_file(), f"chromium failed: {log.read_text()[-2000:]}"
    return cv2.cvtColor(cv2.imread(str(shot)), cv2.COLOR_BGR2RGB)


def predictions(K: torch.Tensor) -> ObjectPredictions:
    boxes = torch.tensor([[20.0, 20.0, 70.0, 80.0], [95.0, 30.0, 150.0, 100.0]])
    z, rho = torch.tensor([2.0, 3.0]), torch.tensor([0.5, 0.8])
    verts, faces = sphere_verts(boxes, K.float(), z, rho, level=2)
    return ObjectPredictions(
        boxes=boxes,
        labels=torch.tensor([0, 2]),
        scores=torch.tensor([0.9, 0.7]),
        z=z,
        rho=rho,
        verts=verts,
        faces=faces,
        instance_ids=torch.full((2,), -1),
    )


@pytest.mark.parametrize("cx", [80.0, 60.0], ids=["centred", "off-centre principal point"])
def test_page_shows_lit_objects_where_K_puts_them_over_the_image(tmp_path, cx):
    width, height = 160, 120
    K = torch.tensor([[150.0, 0.0, cx], [0.0, 150.0, 60.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    image = np.empty((height, width, 3), np.uint8)
    image[:] = IMAGE_RGB
    pred = predictions(K)
    glb = scene_glb(prediction_scene(pred, CATEGORIES, image, K.numpy()), K.numpy(), width, height)
    page = tmp_path / "scene.html"
    page.write_text(viewer_html(glb))
    html = page.read_text()
    fetched = re.findall(r"(?:src|href)\s*=\s*[\"']?(?:https?:)?//[^\"' >]+", html) + re.findall(r"import\s*\(", html)
    assert not fetched, f"the page loads from the network: {fetched[:3]}"  # offline: three.js and the GLB inline
    shot = screenshot(page, SCALE * width, SCALE * height).astype(int)
    assert shot.shape[:2] == (SCALE * height, SCALE * width)

    projected = pred.verts.double() @ K.T
    uv = (projected[..., :2] / projected[..., 2:]).numpy() * SCALE
    covered = np.zeros(shot.shape[:2], bool)
    for n, points in enumerate(uv):
        (x0, y0), (x1, y1) = points.min(0), points.max(0)
        covered[int(y0) : int(np.ceil(y1)), int(x0) : int(np.ceil(x1))] = True
        # the middle half of the projected box: inside the silhouette whatever the tessellation
        cx_, cy_, hw, hh = (x0 + x1) / 2, (y0 + y1) / 2, (x1 - x0) / 4, (y1 - y0) / 4
        inner = shot[int(cy_ - hh) : int(cy_ + hh), int(cx_ - hw) : int(cx_ + hw)].reshape(-1, 3)
        off_image = np.abs(inner - IMAGE_RGB).max(1) > 30
        off_background = np.abs(inner - PAGE_BACKGROUND).max(1) > 30
        assert (off_image & off_background).mean() > 0.95, f"object {n} is not drawn inside its projected box"
        assert inner.mean() > 60, f"object {n} is dark: unlit"
    # everywhere else the input image, in its own colours (unlit), fills the view
    margin = np.zeros_like(covered)
    margin[4:-4, 4:-4] = True
    rest = shot[margin & ~_dilate(covered, 6)]
    assert np.abs(rest - IMAGE_RGB).max(1).mean() < 4


def _dilate(mask: np.ndarray, pixels: int) -> np.ndarray:
    return cv2.dilate(mask.astype(np.uint8), np.ones((2 * pixels + 1, 2 * pixels + 1), np.uint8)) > 0
