"""What the loss alone can teach: fit free meshes (no network) to training samples' masks.

Each object of a sample gets its own ico-sphere vertices in the normalized cube and its own z
and rho, optimised with Adam on exactly the recipe's L_3D + regularizers (``loss.*`` overrides
apply). The silhouette IoUs it reaches (``iou_input``, ``iou_views``, soft silhouettes > 0.5
against the true masks, as logged in training) bound what a network trained with that loss can
learn, and separate loss problems (a fit that stalls here) from network ones (a fit that works
here but not in training). Run it side by side for the settings to compare:

    python scripts/fit_free_meshes.py runs/data --samples 8 --steps 300 loss.render.sigma=4e-3
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from collections import defaultdict

import torch
from tqdm import tqdm

from usl.config import LayoutRange, load_config
from usl.data import CategoryIndex, MultiViewDataset, SampleKey
from usl.geometry import cube_to_frustum, ico_sphere
from usl.losses import combine_losses
from usl.model.multiview_loss import multiview_silhouette_loss, shape_regularizers
from usl.records import RecordsDataset

REPORTED = ("iou_input", "iou_views", "unreached", "xent_gate")


def fit_sample(sample, cfg, steps: int, lr: float, ico_level: int) -> list[dict[str, float]]:
    """Fit one sample's objects; returns the statistics at every step."""
    sphere, faces = ico_sphere(ico_level)
    boxes = sample.frame.boxes[sample.object_rows].float()
    n = len(boxes)
    verts = sphere.expand(n, -1, -1).clone().requires_grad_(True)
    layout = torch.zeros(n, 2, requires_grad=True)  # sigmoid logits of z and rho: mid-range at 0
    K = sample.frame.K.float().expand(n, 3, 3)
    optimizer = torch.optim.Adam([verts, layout], lr=lr)
    weights = replace(cfg.loss.weights, mu_2d=0.0)  # no detector here
    need = {name: bool(getattr(weights, name) * weights.mu_reg) for name in ("edge", "laplacian")}  # no offsets here
    history = []
    for step in range(steps):
        unit = torch.sigmoid(layout)
        z, rho = cfg.model.layout_range.from_unit(unit[:, 0], unit[:, 1])
        silhouette = multiview_silhouette_loss(cube_to_frustum(verts, boxes, K, z, rho), faces, [sample], [n], cfg.loss, step)
        regs = shape_regularizers(verts, [], faces, [n], need)
        total, _ = combine_losses(weights, silhouette.l3d, None, **regs)
        optimizer.zero_grad()
        total.backward()
        optimizer.step()
        history.append({k: float(silhouette.stats[k]) for k in REPORTED if k in silhouette.stats})
    return history


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("data", help="Scene-Shapes records folder")
    p.add_argument("--split", default="train")
    p.add_argument("--config", default="tiny")
    p.add_argument("--samples", type=int, default=8, help="samples fitted (scenes 0..N-1, their first view as input)")
    p.add_argument("--steps", type=int, default=300)
    p.add_argument("--lr", type=float, default=0.01)
    p.add_argument("--ico-level", type=int, default=None, help="sphere level (default: the recipe's)")
    p.add_argument("overrides", nargs="*", help="key=value config overrides")
    args = p.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(args.config, [f"data.root={args.data}", *args.overrides])
    records = RecordsDataset(args.data, args.split)
    cfg.model.layout_range = LayoutRange(**records.manifest["layout"])
    dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), seed=0)
    level = cfg.model.shape.ico_level if args.ico_level is None else args.ico_level
    checkpoints = sorted({args.steps // 4, args.steps // 2, args.steps - 1})
    sums: dict[int, dict[str, list[float]]] = defaultdict(lambda: defaultdict(list))
    first_of_scene = {scene: index for index, (scene, _) in reversed(list(enumerate(dataset.items)))}
    indices = sorted(first_of_scene.values())[: args.samples]
    for index in tqdm(indices, desc="fitting", unit="sample"):
        history = fit_sample(dataset[SampleKey(index, 0)], cfg, args.steps, args.lr, level)
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
