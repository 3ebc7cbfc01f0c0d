"""The ``optim``, ``train`` and ``val`` sections of the config: what the trainer (``usl.engine``) reads."""

from __future__ import annotations

from dataclasses import dataclass

from usl.config_io import ConfigError, check_choice, check_positive


@dataclass
class OptimConfig:
    # "sgd" | "adam" (the paper: SGD on Hypersim and ScanNet, Adam on Scene-Shapes) | "muon" (Muon for
    # the hidden layers' weights, Adam for the rest: usl.engine.muon)
    name: str = "sgd"
    lr: float = 0.01  # base learning rate (for the whole batch of all processes)
    momentum: float = 0.9  # SGD's and Muon's momentum (ignored by Adam)
    weight_decay: float = 1e-4  # L2 penalty on the weights (the paper: 1e-4 with SGD, 0 with Adam)
    steps: tuple[int, ...] = ()  # iterations at which the rate is multiplied by gamma (none: a constant rate)
    gamma: float = 0.1  # factor of each step
    warmup_iters: int = 0  # iterations of a linear warm-up from 0.001 x lr, steadying SGD's first steps (0: none)
    max_iter: int = 1000  # iterations to train (scale optim.steps with it)
    # Clip the whole gradient's norm at this: rare spikes can stall a run (tiny's global shape stage
    # sends some). 0: no clipping.
    clip_grad_norm: float = 0.0

    def __post_init__(self) -> None:
        check_choice("optim.name", self.name, ("sgd", "adam", "muon"))
        if self.name == "muon" and self.weight_decay:
            raise ConfigError(f"optim.weight_decay={self.weight_decay}: muon has no weight decay; set it to 0")
        check_positive("optim.max_iter", self.max_iter)


@dataclass
class TrainConfig:
    batch_size: int = 2  # input images per process (GPU): as many as its memory holds
    seed: int = 0  # seeds data order, sampling and initialisation
    device: str = "auto"  # "auto" (a GPU per process if there are enough, else the CPU) | "cpu" | "cuda"
    amp: str = "bfloat16"  # autocast dtype on CUDA: "bfloat16" | "float16" | "none"; ignored on CPU
    log_every: int = 20  # iterations between rows of metrics.csv and lines of log.txt
    checkpoint_every: int = 1000  # iterations between checkpoints (and one at the end): what a crash can lose
    keep_checkpoints: int = 3  # newest checkpoints kept in the run folder, to bound its disk use (0 keeps all)
    cpu_threads: int = 0  # torch intra-op threads per process (0: torch's default); 1 where processes share cores
    # Stop when more than this fraction of the last 20 steps were skipped as non-finite (corrupt data
    # or divergence, not a rare outlier); 1.0 never stops.
    max_skipped_fraction: float = 0.25

    def __post_init__(self) -> None:
        check_choice("train.amp", self.amp, ("bfloat16", "float16", "none"))
        check_choice("train.device", self.device, ("auto", "cpu", "cuda"))
        check_positive("train.batch_size", self.batch_size)
        if not 0.0 <= self.max_skipped_fraction <= 1.0:
            raise ConfigError(f"train.max_skipped_fraction: {self.max_skipped_fraction} is not in [0, 1]")


@dataclass
class ValidationConfig:
    """Periodic validation during training: a quick subset of ``usl-eval`` on ``data.val_split``."""

    period: int = 500  # iterations between validations, plus one at the end; 0 disables validation
    num_scenes: int = 4  # the first N scenes of the split (0: all); more: steadier figures, slower
    input_views: str = "first"  # input views per scene, as usl-eval --input-views (all | first | every:K | ...)
    samples_3d: int = 1000  # points per mesh for Chamfer / F1 when the split has 3D truth (more: steadier, slower)

    def __post_init__(self) -> None:
        if self.period < 0 or self.num_scenes < 0:
            raise ConfigError(f"val.period and val.num_scenes must be >= 0, got {self.period}, {self.num_scenes}")
