"""The ``data`` section of the config: how training samples are drawn from the records. Beside the loaders that
read it, so ``import usl.data`` (and a ``DataConfig`` in a loader worker) never loads the model."""

from __future__ import annotations

from dataclasses import dataclass

from usl.config_io import ConfigError, check_choice, check_positive


@dataclass
class DataConfig:
    root: str = ""  # records folder (docs/design.md §3)
    train_split: str = "train"  # split the model trains on
    val_split: str = "val"  # split of the periodic validation (``val.*``) and of usl-eval's default
    num_views: int = 5  # M: the input view plus M - 1 other views; more: more supervision per object, slower
    view_sampling: str = "uniform"  # "uniform" | "time_distance" (p ∝ |view_id difference|, video data)
    input_view_stride: int = 1  # every k-th view of a scene is an input view (video data is redundant)
    max_size: int = 0  # resize so the longer image side is at most this (smaller: faster, coarser); 0: as stored
    max_objects: int = 0  # objects of the input view in L_3D (a random subset), to bound crowded scenes; 0 keeps all
    # Probability of mirroring a training sample left-right, all its views as one reflection of the world
    # (usl.data.mirror, the geometry stays exact): more shapes from the same models. 0: never (the paper)
    flip_prob: float = 0.5
    num_workers: int = 2  # data loader processes, so loading overlaps training (0: in the training process)
    verify: str = "size"  # shard checks on open: "size" (a stat) | "sha256" (reads each shard again, to catch damage)

    def __post_init__(self) -> None:
        check_choice("data.view_sampling", self.view_sampling, ("uniform", "time_distance"))
        check_choice("data.verify", self.verify, ("size", "sha256"))
        check_positive("data.num_views", self.num_views)
        check_positive("data.input_view_stride", self.input_view_stride)
        if not 0.0 <= self.flip_prob <= 1.0:
            raise ConfigError(f"data.flip_prob must be in [0, 1], got {self.flip_prob}")
