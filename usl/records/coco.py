"""COCO instances JSON from records: what pycocotools, detectron2 and FiftyOne read.

``export_coco`` writes one split: ``images`` (id, file_name, height, width, plus the records'
scene_id and view_id), ``annotations`` (bbox XYWH, the records' RLE as ``segmentation``, area,
iscrowd 0, category_id, plus instance_id) and ``categories`` (the dataset's ids and names).
``file_name`` is ``<scene_id, URL-quoted>/<view_id:06d>.<png|jpg>`` relative to the image root;
with ``images_dir`` the encoded images are written there, byte for byte, so
``register_coco_instances(name, {}, json_file, images_dir)`` works as it is (RLE masks need
detectron2's ``INPUT.MASK_FORMAT=bitmask``). The JSON is written last and atomically: when it
exists, every image it names has been written.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any
from urllib.parse import quote

from tqdm import tqdm

from usl.errors import UslError

from .atomic import write_json_atomic
from .encode import image_bytes
from .manifest import usl_version
from .reader import RecordsDataset

COLUMNS = ["scene_id", "view_id", "height", "width", "image", "instances"]
VIEWS_PER_READ = 64  # bounds memory for long (video) scenes


def xyxy_to_xywh(box: Sequence[float]) -> list[float]:
    x0, y0, x1, y1 = (float(v) for v in box)
    return [x0, y0, x1 - x0, y1 - y0]


def coco_annotation(
    ann_id: int, image_id: int, category_id: int, rle: dict[str, Any], area: float, box_xyxy: Sequence[float]
) -> dict[str, Any]:
    """A COCO ground-truth annotation (not crowd) from a mask's RLE, pixel count and xyxy box."""
    return {
        "id": int(ann_id),
        "image_id": int(image_id),
        "category_id": int(category_id),
        "segmentation": {"size": [int(v) for v in rle["size"]], "counts": rle["counts"]},
        "area": float(area),
        "bbox": xyxy_to_xywh(box_xyxy),
        "iscrowd": 0,
    }


def image_extension(data: bytes) -> str:
    if data.startswith(b"\x89PNG"):
        return "png"
    if data.startswith(b"\xff\xd8"):
        return "jpg"
    raise UslError("image bytes are neither PNG nor JPEG")


def image_file_name(scene_id: str, view_id: int, data: bytes) -> str:
    return f"{quote(scene_id, safe='')}/{int(view_id):06d}.{image_extension(data)}"


@dataclass
class CocoExport:
    out: Path
    images: int
    annotations: int
    images_dir: Path | None

    def describe(self) -> str:
        where = f"; images in {self.images_dir}" if self.images_dir else ""
        return f"{self.out}: {self.images} images, {self.annotations} annotations (COCO instances){where}"


def export_coco(
    root: str | Path, split: str, out: str | Path, images_dir: str | Path | None = None, progress: bool = False
) -> CocoExport:
    dataset = RecordsDataset(root, split)
    images: list[dict[str, Any]] = []
    annotations: list[dict[str, Any]] = []
    images_dir = Path(images_dir) if images_dir is not None else None
    for scene_id in tqdm(dataset.scene_ids, desc=f"export {split}", unit="scene", disable=not progress):
        total = dataset.num_views(scene_id)
        for start in range(0, total, VIEWS_PER_READ):
            for row in dataset.read_scene(
                scene_id, views=range(start, min(total, start + VIEWS_PER_READ)), columns=COLUMNS
            ):
                data = image_bytes(row["image"])
                try:
                    file_name = image_file_name(row["scene_id"], row["view_id"], data)
                except UslError as exc:
                    raise UslError(f"{dataset.root}: scene {scene_id!r} view {row['view_id']}: {exc}") from None
                image_id = len(images) + 1
                images.append(
                    {
                        "id": image_id,
                        "file_name": file_name,
                        "height": int(row["height"]),
                        "width": int(row["width"]),
                        "scene_id": row["scene_id"],
                        "view_id": int(row["view_id"]),
                    }
                )
                for inst in row["instances"] or []:
                    annotation = coco_annotation(
                        len(annotations) + 1,
                        image_id,
                        inst["category_id"],
                        inst["mask"],
                        inst["area"],
                        inst["box_xyxy"],
                    )
                    annotations.append({**annotation, "instance_id": int(inst["instance_id"])})
                if images_dir is not None:
                    path = images_dir / file_name
                    path.parent.mkdir(parents=True, exist_ok=True)
                    path.write_bytes(data)
    coco = {
        "info": {"description": f"{dataset.manifest['name']} {split} (usl records)", "version": usl_version()},
        "licenses": [],
        "images": images,
        "annotations": annotations,
        "categories": [{"id": int(c["id"]), "name": c["name"]} for c in dataset.categories],
    }
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out, coco, indent=None)
    return CocoExport(out, len(images), len(annotations), images_dir)
