"""Evaluating every predictor on the input views of one scene.

Order of work, chosen so each view's masks are decoded once per scene however many predictors and
input views there are: (1) decode the input views and run every predictor on them; (2) list the
(object, view) pairs each prediction is scored on; (3) walk the needed views in chunks, decode
their true masks, render every prediction into them and score its pairs; (4) 3D metrics against
the objects table when the dataset has one.

Aggregation (documented in docs/design.md §6 terms): an object's "input" value is its score in the input
view; its "views" value is the mean over the other views selected for it (objects absent from a
view are not scored there; objects seen in no other view have no "views" value). Dataset values
are means over objects (``usl.evaluation.summary``), per predictor.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import torch

from usl.data.frames import CategoryIndex, FrameData, decode_frame
from usl.evaluation.baselines import stable_seed
from usl.evaluation.detection import CocoDetections, match_detections
from usl.evaluation.render import DEFAULT_MAX_RENDER_BYTES, detection_masks, score_pairs
from usl.evaluation.targets import META_COLUMNS, decode_view_targets, presence, true_meshes_in_camera
from usl.evaluation.types import EvalInput, Predictor
from usl.evaluation.views import ViewSelection, select_input_views
from usl.geometry import Meshes
from usl.metrics import compare_meshes
from usl.model.outputs import ObjectPredictions
from usl.records import RecordsDataset

Tensor = torch.Tensor


@dataclass
class EvalConfig:
    """How to evaluate (see ``usl-eval --help`` for the meaning of each knob)."""

    input_views: str = "all"  # every view of val is an input, as in the paper
    other_views: str = "auto"
    occlusion: bool = True
    match_iou: float = 0.5
    occluder_score: float = 0.5
    num_samples_3d: int = 10_000
    f1_threshold: float = 0.1
    views_per_chunk: int = 8
    max_render_bytes: int = DEFAULT_MAX_RENDER_BYTES
    batch_size: int = 4
    seed: int = 0
    device: str = "cpu"


@dataclass
class Prediction:
    """One predictor's output on one input view, with its scored pairs."""

    predictor: int
    inp: int  # index into the scene's inputs
    pred: ObjectPredictions  # on the evaluation device; instance_ids matched for detectors
    pairs: dict[int, list[int]] = field(default_factory=dict)  # view position -> object indices scored there
    scores: dict[int, dict[int, tuple[float, float, float]]] = field(
        default_factory=dict
    )  # object -> view -> (IoU, gIoU, depth L1)


@dataclass
class SceneOutcome:
    rows: list[dict[str, Any]]  # one per scored object
    inputs: list[EvalInput]
    positions: list[int]  # scene position of each input
    predictions: list[Prediction]


def evaluate_scene(
    dataset: RecordsDataset,
    scene_id: str,
    predictors: Sequence[Predictor],
    categories: CategoryIndex,
    selection: ViewSelection,
    config: EvalConfig,
    coco: dict[int, CocoDetections],
) -> SceneOutcome:
    """Score every predictor on the scene's input views; detections also go into ``coco[predictor]``."""
    device = torch.device(config.device)
    meta = dataset.read_scene(scene_id, columns=list(META_COLUMNS))
    view_ids = [int(r["view_id"]) for r in meta]
    visible = presence(meta)
    positions = select_input_views(config.input_views, len(meta))
    objects = dataset.read_objects(scene_id)
    encoded = dataset.read_scene(scene_id, views=positions)
    inputs: list[EvalInput] = []
    predictions: list[Prediction] = []
    for start in range(0, len(positions), config.batch_size):
        batch = []
        for row in encoded[start : start + config.batch_size]:
            frame = decode_frame(row, categories, with_image=True, source=dataset.source(scene_id))
            batch.append(EvalInput(frame, true_meshes_in_camera(objects, frame.cam_to_world) if objects else {}))
        for p, predictor in enumerate(predictors):
            with torch.no_grad():
                outputs = predictor(batch)
            for offset, pred in enumerate(outputs):
                i = start + offset
                pred = _checked(pred.to(device), batch[offset], predictor)
                if predictor.uses_detections:
                    pred = _match_and_count(pred, batch[offset], positions[i], meta, config, coco.get(p))
                predictions.append(Prediction(p, i, pred))
        inputs += [replace(inp, frame=release_pixels(inp.frame)) for inp in batch]

    for pr in predictions:
        position = positions[pr.inp]
        ids = pr.pred.instance_ids.tolist()
        chosen = selection(position, view_ids, {iid: visible[iid] for iid in ids if iid >= 0})
        for o, iid in enumerate(ids):
            if iid >= 0:
                for v in [position] + chosen[iid]:
                    pr.pairs.setdefault(v, []).append(o)
    _score_all(meta, inputs, positions, predictions, config, device)
    rows = []
    for pr in predictions:
        rows += _object_rows(
            pr, inputs[pr.inp], positions[pr.inp], predictors[pr.predictor].name, categories, config, device
        )
    return SceneOutcome(rows, inputs, positions, predictions)


def release_pixels(frame: FrameData) -> FrameData:
    """The frame without its image and masks (zero-size views keep their shapes): inputs of a scene
    stay in memory until all its views are scored, and a Hypersim scene has ~100 of them."""
    height, width = frame.size
    return replace(
        frame,
        image=torch.zeros(()).expand(3, height, width),
        masks=torch.zeros((), dtype=torch.bool).expand(len(frame.instance_ids), height, width),
        depth=None,
    )


def _checked(pred: ObjectPredictions, inp: EvalInput, predictor: Predictor) -> ObjectPredictions:
    n = len(pred)
    shapes = {"labels": (n,), "scores": (n,), "z": (n,), "rho": (n,), "instance_ids": (n,)}
    bad = [k for k, s in shapes.items() if tuple(getattr(pred, k).shape) != s]
    if bad or pred.verts.dim() != 3 or pred.verts.shape[0] != n:
        raise ValueError(
            f"predictor {predictor.name!r} returned inconsistent ObjectPredictions (bad: {bad or ['verts']})"
        )
    if not predictor.uses_detections:
        expected = set(inp.frame.instance_ids.tolist())
        got = pred.instance_ids.tolist()
        if len(set(got)) != len(got) or not set(got) <= expected:
            raise ValueError(
                f"predictor {predictor.name!r} must predict ground-truth instances {sorted(expected)} "
                f"of {inp.frame.scene_id}/{inp.frame.view_id}, got {got}"
            )
    return pred


def _match_and_count(
    pred: ObjectPredictions,
    inp: EvalInput,
    position: int,
    meta: list[dict[str, Any]],
    config: EvalConfig,
    coco: CocoDetections | None,
) -> ObjectPredictions:
    frame = inp.frame
    ids = match_detections(pred.boxes, pred.scores, frame.boxes, frame.instance_ids, config.match_iou)
    pred = replace(pred, instance_ids=ids.to(pred.boxes.device))
    if coco is not None:
        view = decode_view_targets(meta[position], position, wanted=(), device=pred.verts.device)
        masks = detection_masks(
            pred.verts, pred.faces, pred.scores, view, config.occluder_score, config.max_render_bytes
        )
        height, width = frame.size
        coco.add_image(
            height, width, frame.labels, frame.masks, pred.labels.cpu(), pred.scores.cpu(), pred.boxes.cpu(), masks
        )
    return pred


def _score_all(
    meta: list[dict[str, Any]],
    inputs: list[EvalInput],
    positions: list[int],
    predictions: list[Prediction],
    config: EvalConfig,
    device: torch.device,
) -> None:
    """Decode the needed views chunk by chunk and score every prediction's pairs that fall in them."""
    wanted: dict[int, set[int]] = {}
    for pr in predictions:
        ids = pr.pred.instance_ids.tolist()
        for v, objects in pr.pairs.items():
            wanted.setdefault(v, set()).update(ids[o] for o in objects)
    needed = sorted(wanted)
    for start in range(0, len(needed), config.views_per_chunk):
        chunk = needed[start : start + config.views_per_chunk]
        views = [decode_view_targets(meta[v], v, wanted[v], device) for v in chunk]
        target = [view.index_of() for view in views]
        for pr in predictions:
            ids = pr.pred.instance_ids.tolist()
            todo = [(o, n, v) for n, v in enumerate(chunk) for o in pr.pairs.get(v, ())]
            if not todo:
                continue
            pairs = torch.tensor([(o, n, target[n][ids[o]]) for o, n, _ in todo], dtype=torch.long)
            pose = inputs[pr.inp].frame.cam_to_world.to(device)
            scored = score_pairs(
                pr.pred.verts, pr.pred.faces, pose, views, pairs, config.occlusion, config.max_render_bytes
            )
            values = zip(scored.iou.tolist(), scored.giou.tolist(), scored.depth_l1.tolist(), strict=True)
            for (o, _, v), value in zip(todo, values, strict=True):
                pr.scores.setdefault(o, {})[v] = value


def _nanmean(values: list[float]) -> float:
    t = torch.tensor(values, dtype=torch.float64)
    return float(torch.nanmean(t)) if len(values) else float("nan")


def _object_rows(
    pr: Prediction,
    inp: EvalInput,
    position: int,
    name: str,
    categories: CategoryIndex,
    config: EvalConfig,
    device: torch.device,
) -> list[dict[str, Any]]:
    """One row per scored object. ``category_id``/``category``: the true class (what per-category means
    group by, so a detector's wrong labels do not move its objects between categories); ``label``/
    ``label_name``: the predicted one. Ids are the dataset's, as in its records and COCO export."""
    pred, frame = pr.pred, inp.frame
    shape3d = _shape_metrics(pred, inp, config, device)
    true_label = dict(zip(frame.instance_ids.tolist(), frame.labels.tolist(), strict=True))
    rows = []
    for o, iid in enumerate(pred.instance_ids.tolist()):
        if iid < 0:
            continue
        own = pr.scores[o][position]
        others = [score for v, score in pr.scores[o].items() if v != position]
        row = {
            "predictor": name,
            "scene_id": frame.scene_id,
            "input_view": frame.view_id,
            "instance_id": iid,
            "category_id": categories.ids[true_label[iid]],
            "category": categories.names[true_label[iid]],
            "label": categories.ids[int(pred.labels[o])],
            "label_name": categories.names[int(pred.labels[o])],
            "score": float(pred.scores[o]),
            "z": float(pred.z[o]),
            "rho": float(pred.rho[o]),
            "mask_iou_input": own[0],
            "box_giou_input": own[1],
            "depth_l1_input": own[2],
            "mask_iou_views": _nanmean([s[0] for s in others]),
            "box_giou_views": _nanmean([s[1] for s in others]),
            "depth_l1_views": _nanmean([s[2] for s in others]),
            "num_views": len(others),
        }
        row.update(shape3d.get(iid, {}))
        rows.append(row)
    return rows


def _shape_metrics(
    pred: ObjectPredictions, inp: EvalInput, config: EvalConfig, device: torch.device
) -> dict[int, dict[str, float]]:
    """Chamfer-L2 and F1@t of each object that has a true mesh, in the input camera frame."""
    ids = pred.instance_ids.tolist()
    chosen = [o for o, iid in enumerate(ids) if iid in inp.true_meshes]
    if not chosen:
        return {}
    frame = inp.frame
    gen = torch.Generator(device=device).manual_seed(stable_seed(config.seed, frame.scene_id, frame.view_id))
    predicted = Meshes.from_shared_topology(pred.verts[chosen], pred.faces)
    true = Meshes(
        [inp.true_meshes[ids[o]].verts.to(device) for o in chosen],
        [inp.true_meshes[ids[o]].faces.to(device) for o in chosen],
    )
    result = compare_meshes(predicted, true, config.num_samples_3d, config.f1_threshold, generator=gen)
    f1_key = f"F1@{config.f1_threshold:g}"
    return {
        ids[o]: {"chamfer": float(result["Chamfer-L2"][n]), "f1": float(result[f1_key][n])}
        for n, o in enumerate(chosen)
    }
