"""What the loss alone can teach: fit free meshes (no network) to training samples' masks.

Each object of a sample gets its own ico-sphere vertices in the normalized cube and its own z
and rho, optimised with Adam on exactly the recipe's L_3D + regularizers (``loss.*`` overrides
apply). The silhouette IoUs it reaches (``iou_input``, ``iou_views``, soft silhouettes > 0.5
against the true masks, as logged in training) bound what a network trained with that loss can
learn, and separate loss problems (a fit that stalls here) from network ones (a fit that works
here but not in training). Run it side by side for the settings to compare:

    python scripts/experiments/fit_free_meshes.py runs/data --samples 8 --steps 300 loss.render.sigma=4e-3

With ``--score OUT`` the fitted meshes are scored as usl-eval scores a model instead (Chamfer, F1,
Mask IoU input and views, per true category, pictures), next to the fixed-depth sphere: an oracle
row fitted to each input view's own scene, e.g. to every view of a held-out Scene-Shapes build
(``data.num_views=8``), which bounds what the mesh (``--ico-level``) can show whatever network
predicts it:

    python scripts/experiments/fit_free_meshes.py HELDOUT --score OUT --input-views every:8 --max-scenes 12 \
        --steps 200 --ico-level 3 data.num_views=8
"""

from __future__ import annotations

import argparse
from collections import defaultdict
from dataclasses import dataclass, replace
from pathlib import Path

import torch
from tqdm import tqdm

from usl.config import load_config
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.evaluation.baselines import spec_baselines
from usl.evaluation.evaluate import dataset_spec, run_evaluation
from usl.evaluation.report import write_report
from usl.evaluation.scene import EvalConfig
from usl.evaluation.types import EvalInput
from usl.geometry import MeshTemplate, cube_to_frustum, ico_sphere
from usl.losses import combine_losses
from usl.model.config import LayoutRange
from usl.model.multiview_loss import REGULARIZERS, multiview_silhouette_loss, shape_regularizers
from usl.model.outputs import ObjectPredictions
from usl.records import RecordsDataset

REPORTED = ("iou_input", "iou_views", "unreached", "xent_gate")


@dataclass
class FittedMeshes:
    verts: torch.Tensor  # (n, V, 3) in the input camera's frame, metres
    faces: torch.Tensor  # (F, 3)
    z: torch.Tensor  # (n,)
    rho: torch.Tensor  # (n,)
    history: list[dict[str, float]]  # the loss statistics at every step


def fit_sample(sample, cfg, steps: int, lr: float, ico_level: int) -> FittedMeshes:
    """Fit one sample's objects (every object of its input view, in ``object_rows`` order)."""
    sphere, faces = ico_sphere(ico_level)
    template = MeshTemplate.build(faces, len(sphere))
    boxes = sample.frame.boxes[sample.object_rows].float()
    n = len(boxes)
    verts = sphere.expand(n, -1, -1).clone().requires_grad_(True)
    layout = torch.zeros(n, 2, requires_grad=True)  # sigmoid logits of z and rho: mid-range at 0
    K = sample.frame.K.float().expand(n, 3, 3)
    optimizer = torch.optim.Adam([verts, layout], lr=lr)
    weights = replace(cfg.loss.weights, mu_2d=0.0)  # no detector here
    need = {name: bool(getattr(weights, name)) for name in REGULARIZERS if name != "offset_l2"}  # no offsets here

    def placed() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        unit = torch.sigmoid(layout)
        z, rho = cfg.model.layout_range.from_unit(unit[:, 0], unit[:, 1])
        return cube_to_frustum(verts, boxes, K, z, rho), z, rho

    history = []
    for step in range(steps):
        silhouette = multiview_silhouette_loss(placed()[0], faces, [sample], [n], cfg.loss, step)
        regs = shape_regularizers(verts, [], template, [n], need)
        total, _ = combine_losses(weights, silhouette.l3d, None, **regs)
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        history.append({k: float(silhouette.stats[k]) for k in REPORTED if k in silhouette.stats})
    with torch.no_grad():
        verts_cam, z, rho = placed()
    return FittedMeshes(verts_cam, faces, z, rho, history)


class FreeMeshOracle:
    """A usl-eval predictor that fits free meshes to each input view's scene (the views
    ``data.num_views`` and ``data.view_sampling`` choose) instead of predicting them: ground-truth boxes,
    no network. Needs every object, unmirrored: ``data.max_objects=0``, ``data.flip_prob=0`` (``main`` sets them)."""

    name = "Free meshes (fitted, oracle)"
    predicts_layout = True
    predicts_shape = True
    uses_detections = False

    def __init__(self, dataset: MultiViewDataset, cfg, steps: int, lr: float, ico_level: int):
        if cfg.data.max_objects or cfg.data.flip_prob:
            raise SystemExit(
                "FreeMeshOracle: fits need data.max_objects=0 and data.flip_prob=0 (mirrored views would be "
                "fitted in a reflected camera frame)"
            )
        self.dataset, self.cfg, self.steps, self.lr, self.ico_level = dataset, cfg, steps, lr, ico_level
        self.index = {item: i for i, item in enumerate(dataset.items)}

    def __call__(self, inputs: list[EvalInput]) -> list[ObjectPredictions]:
        out = []
        for inp in inputs:
            frame = inp.frame
            position = self.dataset.scene_index(frame.scene_id)[0].index(frame.view_id)
            if (frame.scene_id, position) not in self.index:
                raise SystemExit(
                    f"{frame.scene_id} view {frame.view_id} is not an input view of the fitted dataset "
                    "(data.input_view_stride must be 1)"
                )
            with torch.inference_mode(False), torch.enable_grad():  # usl-eval calls predictors without gradients
                sample = self.dataset[self.index[(frame.scene_id, position)]]
                if not torch.equal(sample.frame.instance_ids[sample.object_rows], frame.instance_ids):
                    raise SystemExit(f"{frame.scene_id} view {frame.view_id}: the fitted sample has other objects")
                fit = fit_sample(sample, self.cfg, self.steps, self.lr, self.ico_level)
            n = len(fit.verts)
            out.append(
                ObjectPredictions(
                    boxes=frame.boxes.float(),
                    labels=frame.labels.clone(),
                    scores=torch.ones(n),
                    z=fit.z,
                    rho=fit.rho,
                    verts=fit.verts.float(),
                    faces=fit.faces,
                    instance_ids=frame.instance_ids.clone(),
                )
            )
        return out


def score(args, cfg, dataset: MultiViewDataset, level: int) -> None:
    """Score the fitted meshes with usl-eval next to the fixed-depth sphere; write OUT's report."""
    oracle = FreeMeshOracle(dataset, cfg, args.steps, args.lr, level)
    fixed = spec_baselines(dataset_spec(dataset.records.manifest).get("baselines", {})).get("fixed")
    predictors = [oracle] + ([fixed] if fixed else [])
    config = EvalConfig(input_views=args.input_views, batch_size=1)
    out = Path(args.score)
    run = run_evaluation(
        args.data,
        args.split,
        predictors,
        config,
        max_scenes=args.max_scenes,
        pictures_dir=out / "pictures",
        num_pictures=args.pictures,
    )
    views = {
        key: getattr(cfg.data, key) for key in ("num_views", "view_sampling", "flip_prob", "max_objects")
    }  # as fitted
    header = {
        **run.header,
        "free_mesh_fit": {
            "steps": args.steps,
            "lr": args.lr,
            "ico_level": level,
            "overrides": list(args.overrides),
            "data": views,
        },
    }
    paths = write_report(out, header, run.summaries, run.rows, run.layout, {"pictures": "pictures/index.md"})
    print(f"ico level {level}, {args.steps} steps, overrides: {' '.join(args.overrides) or '(recipe)'}\n")
    print(paths["table"].read_text())


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("data", help="Scene-Shapes records folder")
    p.add_argument("--split", default="train")
    p.add_argument("--config", default="tiny")
    p.add_argument("--samples", type=int, default=8, help="samples fitted (scenes 0..N-1, their first view as input)")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--lr", type=float, default=0.01)
    p.add_argument("--ico-level", type=int, default=None, help="sphere level (default: the recipe's)")
    p.add_argument("--score", metavar="OUT", help="score the fitted meshes as usl-eval does, report into OUT")
    p.add_argument("--input-views", default="every:8", help="with --score: usl-eval's --input-views")
    p.add_argument("--max-scenes", type=int, default=None, help="with --score: the first N scenes")
    p.add_argument("--pictures", type=int, default=6, help="with --score: input views drawn")
    p.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = p.parse_intermixed_args(argv)  # overrides may follow options, as in the examples above
    torch.set_num_threads(1)
    # scoring fits every object of every scored input view, unmirrored, as usl-eval hands it over
    scoring = ["data.max_objects=0", "data.flip_prob=0", "data.input_view_stride=1"] if args.score else []
    cfg = load_config(args.config, [f"data.root={args.data}", *args.overrides, *scoring])  # scoring's settings win
    records = RecordsDataset(args.data, args.split)
    cfg.model.layout_range = LayoutRange(**records.manifest["layout"])
    dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), seed=0)
    level = cfg.model.shape.ico_level if args.ico_level is None else args.ico_level
    if args.score:
        score(args, cfg, dataset, level)
        return
    checkpoints = sorted({args.steps // 4, args.steps // 2, args.steps - 1})
    sums: dict[int, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    first_of_scene = {scene: index for index, (scene, _) in reversed(list(enumerate(dataset.items)))}
    indices = sorted(first_of_scene.values())[: args.samples]
    for index in tqdm(indices, desc="fitting", unit="sample"):
        history = fit_sample(dataset[SampleKey(index, 0)], cfg, args.steps, args.lr, level).history
        for step in checkpoints:
            for key, value in history[step].items():
                sums[step][key].append(value)
    print(f"overrides: {' '.join(args.overrides) or '(recipe)'}; {len(indices)} samples, ico level {level}")
    print("| step | " + " | ".join(REPORTED) + " |")
    print("|---:|" + "---:|" * len(REPORTED))
    for step in checkpoints:
        cells = [f"{sum(v) / len(v):.3f}" if (v := sums[step].get(k)) else "-" for k in REPORTED]
        print(f"| {step + 1} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
