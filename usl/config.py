"""The whole configuration: the sections, each defined beside the code that reads it (``usl.data.config``,
``usl.model.config``, ``usl.engine.config``), composed into one ``Config`` here and loaded from YAML recipes with
``key=value`` overrides (the generic loading machinery is ``usl.config_io``).

A recipe (``usl/configs/<name>.yaml`` or any path) holds only what differs from the dataclass
defaults; ``_base_: other.yaml`` inherits another recipe first. Overrides use dotted keys
(``optim.lr=0.01``, ``model.shape.num_stages=1``) and YAML values (``data.root=/data/hs``,
``optim.steps=[66000,74000]``). Unknown keys and ill-typed values are errors that name the key
and the file, so a typo never silently trains with a default. The resolved config (every field)
is saved in the run folder and in each checkpoint. A saved config may hold keys this version no
longer has (options since removed, docs/experiments/removed-options.md): ``saved_config`` ignores
them with one warning naming them, so old checkpoints still evaluate, predict and resume.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from usl.config_io import (  # noqa: F401  (re-exported: usl.config is where callers import them)
    ConfigError,
    deep_merge,
    drop_unknown_keys,
    from_dict,
    parse_overrides,
    read_yaml_config,
    to_dict,
)
from usl.data.config import DataConfig
from usl.engine.config import OptimConfig, TrainConfig, ValidationConfig
from usl.errors import UslWarning
from usl.model.config import DETECTOR_PRESETS, LossConfig, ModelConfig
from usl.records.atomic import write_text_atomic

CONFIG_DIR = Path(__file__).resolve().parent / "configs"


@dataclass
class Config:
    name: str = "usl"  # the run's name (a recipe's: its file name); default run folder: runs/<name>
    data: DataConfig = field(default_factory=DataConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    loss: LossConfig = field(default_factory=LossConfig)
    optim: OptimConfig = field(default_factory=OptimConfig)
    train: TrainConfig = field(default_factory=TrainConfig)
    val: ValidationConfig = field(default_factory=ValidationConfig)


# --------------------------------------------------------------------------------------------
# The recipes: a checked Config from YAML files and overrides
# --------------------------------------------------------------------------------------------
def resolve_config_path(name_or_path: str | Path) -> Path:
    """A recipe name (``tiny``, ``hypersim``) from ``usl/configs`` or a path to a YAML file."""
    path = Path(name_or_path)
    if path.suffix not in (".yaml", ".yml"):
        path = CONFIG_DIR / f"{name_or_path}.yaml"
    if not path.is_file():
        known = sorted(p.stem for p in CONFIG_DIR.glob("*.yaml"))
        raise ConfigError(f"config {name_or_path!r}: no such file {path} (built-in recipes: {known})")
    return path


def load_config(name_or_path: str | Path, overrides: Sequence[str] = ()) -> Config:
    """Defaults <- recipe (with its ``_base_`` chain) <- overrides, checked and typed.

    A mistake in the recipe is reported against its file; one in the overrides against the
    command line and the override that makes it."""
    path = resolve_config_path(name_or_path)
    recipe = {"name": path.stem, **read_yaml_config(path)}  # a run is named after its recipe unless it says
    config = config_from_dict(recipe, where=str(path))
    return apply_overrides(recipe, overrides) if overrides else config


def apply_overrides(base: Mapping[str, Any], overrides: Sequence[str]) -> Config:
    """``base`` (a valid nested config dict) with command-line ``key=value`` overrides on top."""
    update = parse_overrides(overrides)
    try:
        return config_from_dict(deep_merge(base, update), where="command line")
    except ConfigError as exc:
        culprit = next((o for o in overrides if not _applies(base, o)), None)
        if culprit is None:  # only the combination fails (e.g. a value checked against another)
            raise
        raise ConfigError(f"{exc} (override {culprit!r})") from None


def _applies(base: Mapping[str, Any], override: str) -> bool:
    try:
        config_from_dict(deep_merge(base, parse_overrides([override])))
    except ConfigError:
        return False
    return True


def config_from_dict(data: Mapping[str, Any], where: str = "config") -> Config:
    """A full ``Config`` from a (possibly partial) nested dict over the defaults; an unknown key is an error."""
    defaults = to_dict(Config())
    model = data.get("model") if isinstance(data.get("model"), Mapping) else {}
    preset = model.get("detector_preset", "default")
    if preset not in DETECTOR_PRESETS:
        raise ConfigError(f"{where}: model.detector_preset: {preset!r} is not one of {sorted(DETECTOR_PRESETS)}")
    defaults["model"]["detector"] = to_dict(DETECTOR_PRESETS[preset]())
    merged = deep_merge(defaults, data)
    try:
        return from_dict(Config, merged, "config")
    except ConfigError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def saved_config(data: Mapping[str, Any], where: str) -> Config:
    """The config a checkpoint was saved with. Keys this version no longer has (options measured and
    removed since) are dropped with one ``UslWarning`` naming them: the weights are what a checkpoint
    is kept for, and a saved file cannot be edited the way a recipe or an override can."""
    known, unknown = drop_unknown_keys(Config, data)
    if unknown:
        warnings.warn(
            f"{where}: ignoring saved config key(s) this usl no longer has: {', '.join(unknown)}",
            UslWarning,
            stacklevel=2,
        )
    return config_from_dict(known, where)


def dump_config(config: Config) -> str:
    """The resolved config (every field) as YAML, in definition order."""
    return yaml.safe_dump(to_dict(config), sort_keys=False)


def save_config(config: Config, path: str | Path) -> None:
    """Write the resolved config (every field) as YAML, atomically: a full disk keeps the old file."""
    write_text_atomic(Path(path), dump_config(config))
