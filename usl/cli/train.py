"""``usl-train``: train USL from a recipe, on CPU, one GPU, or many GPUs/machines with torchrun.

    usl-train --config tiny data.root=/data/scene_shapes_small
    usl-train --config hypersim --out runs/hs data.root=/data/hypersim \\
        model.init_weights=/weights/model_final_f10217.pkl
    torchrun --nproc_per_node 8 -m usl.cli.train --config hypersim data.root=...
    torchrun --nnodes 2 --nproc_per_node 8 --rdzv_backend c10d --rdzv_endpoint HOST:PORT --rdzv_id ID \\
        -m usl.cli.train --config hypersim data.root=...   # the same on each machine
    usl-train --resume --out runs/hs                    # continue exactly where it stopped
    usl-train --resume --out runs/hs optim.max_iter=90000
    usl-train --config hypersim --print-config          # the resolved config as YAML; nothing runs
    usl-train --config tiny --list-keys                 # every key: type, value in the recipe, doc line

The run folder gets ``config.yaml`` (the resolved config, ``data.root`` absolute), ``log.txt``
(what the run printed), ``metrics.csv`` (and TensorBoard events beside it with ``usl[tensorboard]``:
``tensorboard --logdir runs/`` shows every run), ``validation.csv`` (periodic validation on
``data.val_split``, keys ``val.*``), ``curves.png`` (losses and one panel per kind of validation
metric against iterations) and ``checkpoints/`` (``usl.engine.checkpoint``).
"""

from __future__ import annotations

import argparse
import os
import re
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from usl.cli.common import common_options, make_parser, warning_lines
from usl.engine.command import COMMAND

if TYPE_CHECKING:
    from usl.config import Config

# The built-in recipes (``usl.config.CONFIG_DIR``, which imports torch: ``--help`` must not)
RECIPES = sorted(path.stem for path in (Path(__file__).resolve().parents[1] / "configs").glob("*.yaml"))
_OVERRIDE = re.compile(r"^[A-Za-z_][\w.]*=")
_SHORTCUTS = {"device": "train.device", "seed": "train.seed", "workers": "data.num_workers"}


def parser() -> argparse.ArgumentParser:
    common = common_options(
        out="run folder (default: runs/<config name>; with --resume: the checkpoint's run folder)",
        workers="data loader processes (shortcut for data.num_workers=N; default: the recipe's)",
        workers_default=None,
        device="shortcut for train.device=... (default: the recipe's)",
        device_default=None,
        seed="shortcut for train.seed=N (default: the recipe's)",
        seed_default=None,
        quiet=None,
    )
    p = make_parser(COMMAND, __doc__, parents=[common])
    p.add_argument("--config", help=f"recipe name ({', '.join(RECIPES)}) or a YAML file")
    p.add_argument(
        "--resume",
        nargs="?",
        const="",
        default=None,
        metavar="CHECKPOINT",
        help="continue from CHECKPOINT, or from the run folder's newest checkpoint",
    )
    show = p.add_mutually_exclusive_group()
    show.add_argument("--print-config", action="store_true", help="print the resolved config as YAML and exit")
    show.add_argument(
        "--list-keys",
        action="store_true",
        help="list every config key with its type, value (in --config, if given) and doc line, and exit",
    )
    p.add_argument("overrides", nargs="*", metavar="key=value", help="config overrides, e.g. optim.lr=0.01")
    return p


def parse_args(argv: Sequence[str] | None = None) -> argparse.Namespace:
    args = parser().parse_args(argv)
    # ``--resume`` takes an optional value, so argparse hands it the next word: a key=value that is
    # not an existing path is an override, never a checkpoint.
    if args.resume and _OVERRIDE.match(args.resume) and not Path(args.resume).exists():
        args.overrides.insert(0, args.resume)
        args.resume = ""
    shortcuts = [f"{key}={getattr(args, name)}" for name, key in _SHORTCUTS.items() if getattr(args, name) is not None]
    args.overrides = shortcuts + args.overrides  # an explicit key=value given too wins
    return args


def resolve_config(args: argparse.Namespace) -> tuple[Config, dict[str, Any] | None]:
    """The config the arguments ask for and, when resuming, the checkpoint payload."""
    from usl.config import ConfigError, apply_overrides, load_config, to_dict
    from usl.engine.checkpoint import checkpoint_config, read_checkpoint

    payload = None
    if args.resume is not None:
        source = args.resume or args.out
        if not source:
            raise ConfigError("--resume needs a checkpoint path or --out")
        payload = read_checkpoint(source)
        stored = checkpoint_config(payload)  # --config is ignored: a resumed run keeps its recipe
        cfg = apply_overrides(to_dict(stored), args.overrides) if args.overrides else stored
    elif args.config:
        cfg = load_config(args.config, args.overrides)
    else:
        raise ConfigError("give --config (a recipe name or YAML file), or --resume")
    if cfg.data.root:  # absolute, so the saved config resumes and evaluates from any folder
        cfg.data.root = str(Path(cfg.data.root).expanduser().resolve())
    return cfg, payload


def resolve_run(args: argparse.Namespace) -> tuple[Config, Path, dict[str, Any] | None]:
    """The config, run folder and (when resuming) checkpoint payload the arguments ask for."""
    cfg, payload = resolve_config(args)
    if payload is not None:
        return cfg, Path(args.out or Path(payload["path"]).parent.parent), payload
    run_dir = Path(args.out or Path("runs") / cfg.name)
    check_new_run(run_dir)
    return cfg, run_dir, None


def check_new_run(run_dir: Path) -> None:
    """Refuse to start a new training in a folder that holds another one's checkpoints."""
    from usl.config import ConfigError
    from usl.engine.checkpoint import CHECKPOINT_DIR

    if (run_dir / CHECKPOINT_DIR).is_dir() and any((run_dir / CHECKPOINT_DIR).glob("model_*.pt")):
        raise ConfigError(f"{run_dir} already holds checkpoints: pass --resume to continue it, or another --out")


def main(argv: Sequence[str] | None = None) -> int:
    args = parse_args(argv)
    from usl.config import ConfigError  # torch loads from here on
    from usl.engine.checkpoint import CheckpointError
    from usl.errors import UslError, error_line

    try:
        # e.g. a resumed checkpoint's saved keys that this usl no longer has: every process of a
        # torchrun training reads the checkpoint, the first one says so
        with warning_lines(COMMAND, show_usl_warnings=os.environ.get("RANK", "0") == "0"):
            run(args)
    except (ConfigError, CheckpointError, UslError) as exc:
        print(f"{COMMAND}: error: {error_line(exc)}", file=sys.stderr)
        return 2
    return 0


def run(args: argparse.Namespace) -> None:
    """What the parsed arguments ask for: the key listing, the resolved config, or the training."""
    from usl.config import Config, dump_config
    from usl.config_docs import format_keys

    if args.list_keys:
        print(format_keys(resolve_config(args)[0] if args.config or args.resume is not None else Config()))
        return
    if args.print_config:
        print(dump_config(resolve_config(args)[0]), end="")
        return
    cfg, run_dir, payload = resolve_run(args)
    from usl.engine.distributed import init_distributed, shutdown_distributed
    from usl.engine.run_folder import hold_run_folder
    from usl.engine.train import Trainer

    info = init_distributed(cfg.train.device)
    try:
        with hold_run_folder(run_dir, info):
            if payload is None:
                check_new_run(run_dir)  # again: another training may have finished there meanwhile
            Trainer(cfg, run_dir, info, payload).train()
    finally:
        shutdown_distributed()


if __name__ == "__main__":  # torchrun -m usl.cli.train ...
    sys.exit(main())
