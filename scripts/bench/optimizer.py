"""Optimizer-step benchmark: CPU milliseconds of one step over a recipe's model, per optimizer.

    python scripts/bench/optimizer.py --config tiny                 # adam and muon, one thread
    python scripts/bench/optimizer.py --config tiny --optimizers muon sgd --steps 50

Every optimizer steps the same model's parameters with the same random gradients, through
``GradScaler`` as usl-train does (every parameter has one here; in training an unused one, such as
the backbone's ImageNet classifier, has none, so this is an upper bound); the optimizers take turns step by step, so a busy machine slows
them alike. Prints each one's CPU ms per step and its ratio to the first.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # the checkout: its tests' recipe configs

from tests.data.synthetic_samples import synthetic_config  # noqa: E402
from usl.engine.optim import build_optimizer  # noqa: E402
from usl.model.usl_model import USLModel  # noqa: E402


def optimizer_for(config: str, name: str) -> tuple[torch.optim.Optimizer, torch.amp.GradScaler]:
    # the recipe's dataset's categories and depth range (synthetic_config): the model needs them
    cfg = synthetic_config(config, [f"optim.name={name}", *(["optim.weight_decay=0"] if name == "muon" else [])])
    torch.manual_seed(0)
    model = USLModel(cfg.model, cfg.loss, load_init_weights=False)
    model.lay_out_weights_like_features(torch.device("cpu"))
    optimizer = build_optimizer(model.named_parameters(), cfg.optim, model.lr_factors(), model.prediction_weights())
    for param in model.parameters():
        param.grad = torch.randn_like(param) * 1e-3
    return optimizer, torch.amp.GradScaler("cpu", init_scale=1.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="tiny")
    parser.add_argument("--optimizers", nargs="+", default=["adam", "muon"], choices=["adam", "muon", "sgd"])
    parser.add_argument("--steps", type=int, default=30, help="timed steps per optimizer")
    parser.add_argument("--threads", type=int, default=1, help="CPU intra-op threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    runs = {name: optimizer_for(args.config, name) for name in args.optimizers}
    cpu = dict.fromkeys(runs, 0.0)
    for step in range(args.steps + 2):  # two untimed warm-up steps
        for name, (optimizer, scaler) in runs.items():
            start = time.process_time()
            scaler.scale(torch.ones(()))
            scaler.step(optimizer)
            scaler.update(1.0)
            if step >= 2:
                cpu[name] += time.process_time() - start
    first = args.optimizers[0]
    for name, seconds in cpu.items():
        print(f"{name:5s} {1e3 * seconds / args.steps:7.1f} ms CPU per step  ({seconds / cpu[first]:.1f}x {first})")


if __name__ == "__main__":
    main()
