"""What the per-object diagnostic scripts share: their command line, the trained model, and the
input views of a build, resized for that model (``mask_head_iou.py``, ``placement_chamfer.py``)."""

from __future__ import annotations

import argparse
from collections.abc import Iterator
from typing import Any

from tqdm import tqdm

from usl.data.frames import CategoryIndex, FrameData, decode_frame
from usl.evaluation.model import frames_for_model, load_checkpoint_model
from usl.evaluation.views import select_input_views
from usl.records import RecordsDataset


def parse_args(description: str) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("data", help="records folder")
    parser.add_argument("checkpoint", help="run folder or checkpoint file")
    parser.add_argument("--split", default="train")
    parser.add_argument("--input-views", default="every:8")
    return parser.parse_args()


def load_model(args: argparse.Namespace) -> tuple[Any, Any]:
    """The checkpoint's model in eval mode on the CPU, and its config."""
    model, cfg = load_checkpoint_model(args.checkpoint, "cpu")
    return model.eval(), cfg


def input_frames(args: argparse.Namespace, max_size: int) -> Iterator[tuple[FrameData, list[dict[str, Any]]]]:
    """(frame, the scene's objects table) for every selected input view with at least one object."""
    dataset = RecordsDataset(args.data, args.split)
    categories = CategoryIndex(dataset.categories)
    for scene_id in tqdm(dataset.scene_ids, desc="scenes", unit="scene"):
        objects = dataset.read_objects(scene_id)
        positions = select_input_views(args.input_views, dataset.num_views(scene_id))
        for row in dataset.read_scene(scene_id, views=positions):
            (frame,) = frames_for_model([decode_frame(row, categories, source=dataset.source(scene_id))], max_size)
            if len(frame.boxes):
                yield frame, objects
