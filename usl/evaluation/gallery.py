"""The pictures of an evaluation run: which input views get one, and ``pictures/index.md``.

Two ways to choose (``usl-eval --pictures N --pictures-by ...``):

* ``spread`` (default): N input views spread evenly over the split's scenes (the first input view
  of each chosen scene, more per scene only when N exceeds the scenes), drawn as the scenes pass;
* ``extremes``: the N/2 worst and N/2 best input views by the mean Mask IoU (views) of the first
  predictor's objects; their scenes are evaluated once more to draw them (the numbers are
  deterministic, so the pictures show exactly what ``objects.jsonl`` holds).

Each picture is drawn for every predictor. The index page lists the pictures with their scene,
view, the ``objects.jsonl`` lines of their objects and those objects' Mask IoU.
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch

from usl.data.frames import CategoryIndex
from usl.errors import UslError
from usl.evaluation.choices import PICTURE_SELECTIONS
from usl.evaluation.pictures import evaluation_picture
from usl.evaluation.scene import EvalConfig, SceneOutcome, evaluate_scene
from usl.evaluation.types import Predictor
from usl.evaluation.views import ViewSelection
from usl.records import RecordsDataset, frame_pose
from usl.vis.visualize import write_png

INDEX_NAME = "index.md"


def slug(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9._-]+", "_", text).strip("_") or "x"


def spread_counts(num_scenes: int, count: int) -> list[int]:
    """Pictures per scene: ``count`` spread evenly over ``num_scenes`` scenes."""
    counts = [0] * num_scenes
    if num_scenes == 0:
        return counts
    for index in np.linspace(0, num_scenes - 1, min(count, num_scenes)).round().astype(int):
        counts[index] += 1
    for extra in range(count - min(count, num_scenes)):  # more pictures than scenes: a second round
        counts[round(extra * num_scenes / max(count - num_scenes, 1)) % num_scenes] += 1
    return counts


def mean_iou_views(rows: Sequence[dict[str, Any]]) -> float:
    values = [
        r["mask_iou_views"] for r in rows if r.get("mask_iou_views") is not None and math.isfinite(r["mask_iou_views"])
    ]
    return sum(values) / len(values) if values else math.nan


@dataclass
class Picture:
    path: Path  # relative to the pictures folder
    predictor: str
    scene_id: str
    input_view: int
    keys: list[tuple[str, str, int, int]]  # (predictor, scene, view, instance) of its objects' rows


class Gallery:
    """Draws the chosen pictures and writes the index; ``out_dir`` is the ``pictures`` folder."""

    def __init__(
        self,
        out_dir: Path,
        count: int,
        selection: str,
        predictors: Sequence[Predictor],
        categories: CategoryIndex,
        score_threshold: float,
    ):
        if selection not in PICTURE_SELECTIONS:
            raise UslError(f"--pictures-by {selection!r}: choose from {', '.join(PICTURE_SELECTIONS)}")
        self.out_dir, self.count, self.selection = out_dir, count, selection
        self.predictors, self.categories, self.score_threshold = predictors, categories, score_threshold
        self.pictures: list[Picture] = []
        self.per_scene: list[int] = []
        self.inputs: dict[tuple[str, int], int] = {}  # (scene, view id) -> scene position, for "extremes"

    def start(self, num_scenes: int) -> None:
        self.per_scene = spread_counts(num_scenes, self.count) if self.selection == "spread" else [0] * num_scenes

    def scene_done(self, dataset: RecordsDataset, scene_index: int, outcome: SceneOutcome) -> None:
        """Called for every scene as it is evaluated."""
        for inp, position in zip(outcome.inputs, outcome.positions, strict=True):
            self.inputs[(inp.frame.scene_id, inp.frame.view_id)] = position
        wanted = self.per_scene[scene_index] if scene_index < len(self.per_scene) else 0
        if wanted:
            chosen = sorted({int(i) for i in np.linspace(0, len(outcome.inputs) - 1, min(wanted, len(outcome.inputs)))})
            self.draw(dataset, outcome, chosen)

    def finish(
        self, dataset: RecordsDataset, rows: Sequence[dict[str, Any]], selection: ViewSelection, config: EvalConfig
    ) -> None:
        """``extremes``: rank the input views, evaluate their scenes again and draw them."""
        if self.selection != "extremes" or not self.count or not self.predictors:
            return
        first = self.predictors[0].name
        by_input: dict[tuple[str, int], list[dict[str, Any]]] = {}
        for row in rows:
            if row["predictor"] == first:
                by_input.setdefault((row["scene_id"], row["input_view"]), []).append(row)
        ranked = sorted((v, k) for k, r in by_input.items() if not math.isnan(v := mean_iou_views(r)))
        worst = [k for _, k in ranked[: self.count // 2]]
        best = [k for _, k in ranked[::-1][: self.count - len(worst)] if k not in worst]
        scenes: dict[str, list[int]] = {}
        for scene_id, view_id in worst + best:
            scenes.setdefault(scene_id, []).append(self.inputs[(scene_id, view_id)])
        for scene_id, positions in scenes.items():
            only = replace(config, input_views="positions:" + ",".join(map(str, sorted(positions))))
            outcome = evaluate_scene(dataset, scene_id, self.predictors, self.categories, selection, only, {})
            self.draw(dataset, outcome, list(range(len(outcome.inputs))))

    def draw(self, dataset: RecordsDataset, outcome: SceneOutcome, chosen: Sequence[int]) -> None:
        if not outcome.inputs:
            return
        scene_id = outcome.inputs[0].frame.scene_id
        poses = [torch.from_numpy(frame_pose(r)) for r in dataset.read_scene(scene_id, columns=["cam_to_world"])]
        for pr in outcome.predictions:
            if pr.inp not in chosen:
                continue
            inp, predictor = outcome.inputs[pr.inp], self.predictors[pr.predictor]
            view_id = inp.frame.view_id
            own = {
                r["instance_id"]: r
                for r in outcome.rows
                if r["predictor"] == predictor.name and r["input_view"] == view_id
            }
            picture = evaluation_picture(
                dataset,
                inp,
                outcome.positions[pr.inp],
                pr.pred,
                predictor.name,
                self.categories,
                poses,
                own,
                predictor.uses_detections,
                self.score_threshold,
            )
            path = Path(slug(predictor.name)) / f"{slug(scene_id)}_view{view_id:05d}.png"
            write_png(self.out_dir / path, picture)
            keys = [(predictor.name, scene_id, view_id, int(i)) for i in sorted(own)]
            self.pictures.append(Picture(path, predictor.name, scene_id, view_id, keys))

    def write_index(self, rows: Sequence[dict[str, Any]], objects_file: str = "../objects.jsonl") -> Path | None:
        """``index.md``: every picture with its objects' lines in ``objects.jsonl`` (1-based)."""
        if not self.pictures:
            return None
        line_of = {
            (r["predictor"], r["scene_id"], r["input_view"], r["instance_id"]): n + 1 for n, r in enumerate(rows)
        }
        how = (
            "spread evenly over the scenes"
            if self.selection == "spread"
            else f"the worst and best by the mean Mask IoU (views) of {self.predictors[0].name}"
        )
        lines = [
            f"# Evaluation pictures ({len(self.pictures)})",
            "",
            f"Input views {how}; detections drawn from score {self.score_threshold:g}. "
            f"Rows are line numbers of [objects.jsonl]({objects_file}).",
            "",
        ]
        for name in dict.fromkeys(p.predictor for p in self.pictures):
            lines += [
                f"## {name}",
                "",
                "| picture | scene | input view | objects.jsonl rows | Mask IoU input | Mask IoU views |",
                "|:---|:---|:---:|:---:|:---:|:---:|",
            ]
            for picture in (p for p in self.pictures if p.predictor == name):
                numbers = [line_of[k] for k in picture.keys if k in line_of]
                scored = [rows[n - 1] for n in numbers]
                iou_in = [r["mask_iou_input"] for r in scored if r.get("mask_iou_input") is not None]
                iou_in_text = f"{sum(iou_in) / len(iou_in):.3f}" if iou_in else "–"
                views = mean_iou_views(scored)
                lines.append(
                    f'| <a href="{picture.path.as_posix()}"><img src="{picture.path.as_posix()}" width="480"></a> '
                    f"| {picture.scene_id} | {picture.input_view} | {', '.join(map(str, numbers)) or '–'} "
                    f"| {iou_in_text} | {'–' if math.isnan(views) else f'{views:.3f}'} |"
                )
            lines.append("")
        path = self.out_dir / INDEX_NAME
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text("\n".join(lines))
        return path
