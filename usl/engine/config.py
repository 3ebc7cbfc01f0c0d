"""The ``optim``, ``train`` and ``val`` sections of the config: what the trainer (``usl.engine``) reads."""

from __future__ import annotations

from dataclasses import dataclass, field

from usl.config_io import ConfigError, check_choice, check_positive


@dataclass
class OptimConfig:
    name: str = "sgd"  # "sgd" | "adam"
    lr: float = 0.01  # base learning rate (for the whole batch of all processes)
    momentum: float = 0.9  # SGD momentum (ignored by Adam)
    weight_decay: float = 1e-4  # L2 penalty on the weights
    schedule: str = "step"  # "step" (x gamma at each of steps) | "constant"
    steps: tuple[int, ...] = ()  # iterations at which the "step" schedule multiplies the rate by gamma
    gamma: float = 0.1  # factor of each step
    warmup_iters: int = 0  # linear warm-up length (0: none)
    warmup_factor: float = 0.001  # rate at iteration 0 of the warm-up, as a fraction of lr
    max_iter: int = 1000  # iterations to train
    # Clip the whole gradient's norm at this, against rare gradient spikes after which a run can stall
    # (tiny's global stage sends them). 0 disables clipping (the norm is still checked for NaN/inf).
    clip_grad_norm: float = 0.0
    # Learning-rate factors by parameter-name prefix, e.g. {shape_head: 10}: the longest matching
    # prefix wins, other parameters keep lr. Empty: one rate for the whole model (the paper).
    lr_mult: dict[str, float] = field(default_factory=dict)

    def __post_init__(self) -> None:
        check_choice("optim.name", self.name, ("sgd", "adam"))
        check_choice("optim.schedule", self.schedule, ("step", "constant"))
        check_positive("optim.max_iter", self.max_iter)
        bad = {k: v for k, v in self.lr_mult.items() if not v > 0}
        if bad:
            raise ConfigError(f"optim.lr_mult: factors must be > 0, got {bad}")


@dataclass
class TrainConfig:
    batch_size: int = 2  # input images per process (GPU)
    seed: int = 0  # seeds data order, sampling and initialisation
    device: str = "auto"  # "auto" (a GPU per process if there are enough, else the CPU) | "cpu" | "cuda"
    amp: str = "bfloat16"  # autocast dtype on CUDA: "bfloat16" | "float16" | "none"; ignored on CPU
    log_every: int = 20  # iterations between rows of metrics.csv and lines of log.txt
    checkpoint_every: int = 1000  # iterations between checkpoints (and one at the end)
    keep_checkpoints: int = 3  # newest checkpoints kept in the run folder (0 keeps all)
    cpu_threads: int = 0  # torch intra-op threads per process; 0 leaves torch's default
    # On CPU, keep freed heap memory in the process (glibc's mmap and trim thresholds raised by
    # TrainStep, usl.engine.cpu_memory): steps stop re-faulting their tensors page by page. The
    # process keeps its peak memory; false leaves glibc's defaults.
    retain_freed_memory: bool = True
    # Stop when more than this fraction of the last ``skip_window`` steps were skipped as non-finite
    # (corrupt data or divergence, not a rare outlier); 1.0 never stops.
    max_skipped_fraction: float = 0.25
    skip_window: int = 20  # recent steps the skipped fraction is counted over

    def __post_init__(self) -> None:
        check_choice("train.amp", self.amp, ("bfloat16", "float16", "none"))
        check_choice("train.device", self.device, ("auto", "cpu", "cuda"))
        check_positive("train.batch_size", self.batch_size)
        check_positive("train.skip_window", self.skip_window)
        if not 0.0 <= self.max_skipped_fraction <= 1.0:
            raise ConfigError(f"train.max_skipped_fraction: {self.max_skipped_fraction} is not in [0, 1]")


@dataclass
class ValidationConfig:
    """Periodic validation during training: a quick subset of ``usl-eval`` on ``data.val_split``."""

    period: int = 500  # iterations between validations, plus one at the end; 0 disables validation
    num_scenes: int = 4  # the first N scenes of the split (0: all)
    input_views: str = "first"  # input views per scene, as usl-eval --input-views (all | first | every:K | ...)
    samples_3d: int = 1000  # points per mesh for Chamfer / F1 when the split has 3D ground truth

    def __post_init__(self) -> None:
        if self.period < 0 or self.num_scenes < 0:
            raise ConfigError(f"val.period and val.num_scenes must be >= 0, got {self.period}, {self.num_scenes}")
