"""Why does the vertex sampler hardly matter here (Table 1's "USL (5 views)" against "w/o RoIMap")?

The sampler (RoIMap: each vertex's projection into the whole image's maps; VertAlign: into a 14²
RoIAlign grid of the box) only feeds the refinement stages; a recipe with a global stage draws the
shape first from the box's RoIAlign features, whatever the sampler. Each RUN's scored checkpoint
is scored three ways by usl-eval, on every input view of each held-out build:
- ``as trained``;
- ``global stage only``: the refinement stages' offset layers zeroed, so each mesh is the global
  stage's (what the sampler cannot change);
- ``other sampler``: the same weights reading the vertex features through the other sampler
  (neither sampler has weights);
- ``no vertex features``: the refinement stages' bottleneck weights zeroed (their biases kept), so
  the stages see each vertex's position but nothing sampled from the image.
The gap from "global stage only" to "as trained" is what the refinement stages draw; the gap from
"no vertex features" to "as trained" the part of it that reads the image, the only part a sampler
can change; the gap to "other sampler" what the sampler changes of it.

    python3 scripts/experiments/sampler_why.py RUN [RUN ...] --out DIR --heldout H1 [H2 ...]

DIR gets each variant's checkpoint, usl-eval's reports (DIR/<run name>/<variant>/seed<k>) and
``table.md``; a variant scored before is not scored again.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import torch
from table1_summary import TABLE_COLUMNS, scored_checkpoint  # a sibling script

from usl.evaluation.report import builds_summary, mean_std, read_builds, row_values
from usl.records.atomic import write_text_atomic

VARIANTS = ("as trained", "global stage only", "other sampler", "no vertex features")
OTHER = {"roimap": "vertalign", "vertalign": "roimap"}


def variant_payload(payload: dict, variant: str) -> dict:
    """A copy of the checkpoint ``payload`` changed as ``variant`` says (the weights it keeps are the same)."""
    payload = {**payload, "model": dict(payload["model"]), "config": json.loads(json.dumps(payload["config"]))}
    shape = payload["config"]["model"]["shape"]
    if variant == "global stage only":
        if not shape["global_stage"]:
            raise SystemExit("sampler_why.py: the recipe has no global stage (model.shape.global_stage=0)")
        for name, value in payload["model"].items():
            if name.startswith("shape_head.stages.") and ".offset." in name:
                payload["model"][name] = torch.zeros_like(value)
    elif variant == "other sampler":
        shape["sampler"] = OTHER[shape["sampler"]]
    elif variant == "no vertex features":
        for name, value in payload["model"].items():
            if name.startswith("shape_head.stages.") and name.endswith(".bottleneck.weight"):
                payload["model"][name] = torch.zeros_like(value)
    return payload


def score(checkpoint: Path, heldout: list[Path], out: Path) -> dict:
    """usl-eval of ``checkpoint`` on each held-out build (as table1.sh scores a run); the summary over them."""
    for build in heldout:
        report = out / build.name
        if (report / "metrics.json").is_file():
            continue
        command = [sys.executable, "-m", "usl.cli.evaluate", str(build), "--split", "train", "--input-views", "all"]
        command += ["--device", "cpu", "--out", str(report), "--quiet", "--pictures", "0"]
        command += ["--checkpoint", str(checkpoint), "--rows", "model"]
        log = out / f"{build.name}.log"  # usl-eval's report, as table1.sh keeps it
        with log.open("w") as stream:
            if subprocess.run(command, stdout=stream, stderr=subprocess.STDOUT).returncode:
                raise SystemExit(f"sampler_why.py: usl-eval failed on {build} with {checkpoint} (see {log})")
    builds = read_builds(out)
    return builds_summary(builds, row_values(builds, TABLE_COLUMNS))


def row(name: str, summary: dict) -> str:
    (figures,) = summary["rows"].values()
    cells = []
    for column in TABLE_COLUMNS:
        mean, _ = mean_std(figures[column.metric]["values"])
        cells.append(f"{mean * column.scale:.{column.decimals}f}")
    return f"| {name} | " + " | ".join(cells) + " |"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="usl-train output folders")
    parser.add_argument("--heldout", nargs="+", type=Path, required=True, help="held-out builds (seed<k> folders)")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    lines = ["| Run, variant | " + " | ".join(c.title for c in TABLE_COLUMNS) + " |"]
    lines.append("|:---|" + ":---:|" * len(TABLE_COLUMNS))
    for run in args.runs:
        checkpoint, _ = scored_checkpoint(run)
        payload = torch.load(checkpoint, map_location="cpu", weights_only=True)
        name = "_".join(run.resolve().parts[-3:-1])  # <row>_<seed> of table1.sh's runs/<row>/seed<k>/train
        sampler = payload["config"]["model"]["shape"]["sampler"]
        for variant in VARIANTS:
            folder = args.out / name / variant.replace(" ", "_")
            folder.mkdir(parents=True, exist_ok=True)
            scored = checkpoint
            if variant != "as trained":
                scored = folder / "model.pt"
                if not scored.is_file():
                    torch.save(variant_payload(payload, variant), scored)
            label = f"{name} ({sampler}), {variant}" + (f": {OTHER[sampler]}" if variant == "other sampler" else "")
            lines.append(row(label, score(scored, args.heldout, folder)))
            print(lines[-1], flush=True)
    write_text_atomic(args.out / "table.md", "\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
