"""``usl-train`` end to end on tiny synthetic records: exact resume, DDP equivalence, NaN guard, errors."""

import os
import subprocess
import sys
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import pytest
import torch

from tests.data.synthetic_records import build_synthetic_records
from usl.cli.train import main
from usl.config import load_config
from usl.engine.checkpoint import CheckpointError, load_model, read_checkpoint
from usl.engine.distributed import DistInfo
from usl.engine.run_log import read_metrics
from usl.engine.skip_guard import TooManySkippedSteps
from usl.engine.train import Meter, Trainer, seed_everything
from usl.model.outputs import ObjectPredictions
from usl.model.usl_model import USLModel

REPO = Path(__file__).parents[2]
FAST = [
    "train.cpu_threads=1",
    "data.max_size=0",
    "data.num_views=2",
    "loss.mesh_points=100",
    "loss.render.resolution=16",
    "model.shape.num_stages=1",
]


@pytest.fixture(scope="module")
def records(tmp_path_factory):
    return build_synthetic_records(tmp_path_factory.mktemp("train") / "records", num_scenes=4, num_views=4, size=48)


def _args(records, out, *overrides):
    return ["--config", "tiny", "--out", str(out), f"data.root={records}", *FAST, *overrides]


def _weights(path):
    return read_checkpoint(path)["model"]


def test_resume_reproduces_the_uninterrupted_run(records, tmp_path):
    """Interrupted after its iteration-3 checkpoint (it ran on to 4), then resumed: same losses
    and the same final weights as a run that never stopped, across an epoch boundary (4 per epoch)."""
    common = ["train.batch_size=4", "train.log_every=1", "train.checkpoint_every=3", "train.keep_checkpoints=0"]
    assert main(_args(records, tmp_path / "full", *common, "optim.max_iter=6")) == 0
    assert main(_args(records, tmp_path / "cut", *common, "optim.max_iter=4")) == 0
    assert main(["--resume", str(tmp_path / "cut" / "checkpoints" / "model_0000003.pt"), "optim.max_iter=6"]) == 0
    full, resumed = read_metrics(tmp_path / "full"), read_metrics(tmp_path / "cut")
    assert [r["iteration"] for r in resumed] == [1, 2, 3, 4, 5, 6] and [r["epoch"] for r in full][-1] == 1
    for a, b in zip(full, resumed, strict=True):
        for key in ("loss", "l3d", "det/loss_cls", "det/loss_rpn_cls", "stat/l_dist", "grad_norm"):
            assert a[key] == pytest.approx(b[key], rel=1e-6, abs=1e-9), (a["iteration"], key)
    end_full = _weights(tmp_path / "full" / "checkpoints" / "model_0000006.pt")
    end_resumed = _weights(tmp_path / "cut")  # the run folder resolves to its newest checkpoint
    for name, value in end_full.items():
        assert torch.allclose(value.float(), end_resumed[name].float(), atol=1e-6), name
    model, config = load_model(tmp_path / "cut")
    assert not model.training and config.optim.max_iter == 6 and config.model.categories == ("crate", "slab")
    assert (tmp_path / "cut" / "config.yaml").is_file()


def test_training_feedback_files(records, tmp_path, monkeypatch, capsys):
    """log.txt, validation.csv, curves.png and the summary of a 4-iteration run started with a
    relative data.root (saved absolute, so the run resumes from anywhere); and no warning on the
    way: none of usl's, and none of a library's that Python's default filters would show a user."""
    monkeypatch.chdir(records.parent)
    out = tmp_path / "fb"
    argv = [
        "--config",
        "tiny",
        "--out",
        str(out),
        f"data.root={records.name}",
        *FAST,
        "train.batch_size=2",
        "optim.max_iter=4",
        "train.log_every=2",
        "train.checkpoint_every=2",
        "val.period=2",
        "val.num_scenes=1",
    ]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert main(argv) == 0
    hidden = (DeprecationWarning, PendingDeprecationWarning, ImportWarning, ResourceWarning)  # outside __main__
    shown = [w for w in caught if not issubclass(w.category, hidden) or w.filename.startswith(str(REPO / "usl"))]
    assert [f"{w.filename}:{w.lineno}: {w.category.__name__}: {w.message}" for w in shown] == []
    printed = capsys.readouterr().out
    cfg = load_config(out / "config.yaml")
    assert cfg.data.root == str(records.resolve())
    params = sum(p.numel() for p in load_model(out)[0].parameters())
    log = (out / "log.txt").read_text()
    assert f"{params:,} parameters" in log and f"{params:,} parameters" in printed
    assert log.count("iter 2/4") == 1 and log.count("validation at iteration") == 2
    summary = log.strip().splitlines()[-1]
    assert "finished at iteration 4" in summary and "model_0000004.pt" in summary and "curves.png" in summary
    assert summary.split("] ", 1)[1] in printed
    rows = read_metrics(out, "validation.csv")
    assert [r["iteration"] for r in rows] == [2, 4]
    assert all(0.0 <= r["val/mask_iou_input"] <= 1.0 and 0.0 <= r["val/mask_iou_views"] <= 1.0 for r in rows)
    assert rows[0]["val/chamfer"] > 0  # the synthetic records have 3D ground truth
    curves = cv2.imread(str(out / "curves.png"))
    assert curves is not None and curves.shape[0] > 600 and curves.std() > 10  # several panels, not a blank canvas
    _check_tensorboard(out, summary)

    monkeypatch.chdir(tmp_path)  # another folder: the absolute root still resolves
    assert main(["--resume", f"data.root={records}", "--out", str(out), "optim.max_iter=5", "val.period=0"]) == 0
    assert load_config(out / "config.yaml").optim.max_iter == 5
    assert "resuming at iteration 4" in (out / "log.txt").read_text()


def _check_tensorboard(run_dir, summary):
    """TensorBoard's own readers find the run at the top of its parent folder, with the CSV logs' values."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
    from tensorboard.backend.event_processing.plugin_event_multiplexer import EventMultiplexer

    assert f"TensorBoard events (tensorboard --logdir {run_dir.parent})" in summary
    runs = EventMultiplexer().AddRunsFromDirectory(str(run_dir.parent)).Reload().Runs()
    assert run_dir.name in runs  # `tensorboard --logdir runs/` lists the run by its folder name
    events = EventAccumulator(str(run_dir)).Reload()
    for csv_name, key in (("metrics.csv", "loss"), ("validation.csv", "val/mask_iou_input")):
        logged = {int(r["iteration"]): r[key] for r in read_metrics(run_dir, csv_name)}
        scalars = {e.step: e.value for e in events.Scalars(key)}
        assert scalars.keys() == logged.keys() and all(
            scalars[i] == pytest.approx(v, rel=1e-6) for i, v in logged.items()
        ), key


def test_two_process_ddp_step_equals_one_process_on_the_combined_batch(records, tmp_path):
    """One SGD step (lr 0.1, no momentum): weights after it hold the averaged gradient. Detection
    losses are off (their proposal sampling draws per-process random numbers) and BatchNorm is
    frozen (batch statistics differ by construction)."""
    common = [
        "optim.name=sgd",
        "optim.lr=0.1",
        "optim.momentum=0",
        "optim.weight_decay=0",
        "optim.max_iter=1",
        "optim.steps=[]",
        "loss.weights.mu_2d=0",
        "model.detector.backbone.resnet.norm=FrozenBN",
        "data.num_views=3",
        "model.shape.num_stages=2",
        "val.period=0",
    ]
    assert main(_args(records, tmp_path / "one", *common, "train.batch_size=2")) == 0
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    command = [
        sys.executable,
        "-m",
        "torch.distributed.run",
        "--standalone",
        "--nproc_per_node=2",
        "-m",
        "usl.cli.train",
        *_args(records, tmp_path / "two", *common, "train.batch_size=1"),
    ]
    result = subprocess.run(command, env=env, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert result.returncode == 0, result.stderr[-3000:]
    one, two = _weights(tmp_path / "one"), _weights(tmp_path / "two")
    for name, value in one.items():  # float32 summation order differs: compare at each tensor's scale
        assert (value - two[name]).abs().max() <= 1e-5 * value.abs().max() + 1e-7, name
    assert read_checkpoint(tmp_path / "two")["world_size"] == 2
    # the step did move the heads and the backbone (the trainer seeds, then builds the model)
    _, config = load_model(tmp_path / "one")
    seed_everything(config.train.seed, 0)
    initial = USLModel(config.model, config.loss).state_dict()
    for prefix in ("layout_head.", "shape_head.", "detector.backbone.fpn."):
        assert any(not torch.equal(v, initial[k]) for k, v in one.items() if k.startswith(prefix)), prefix


def test_every_gradient_arrives_in_its_parameters_layout(records, tmp_path):
    """On the CPU the backbone's maps are channels-last, and so are their convolutions' weight
    gradients: the trainer's model holds those weights channels-last too, so autograd keeps each
    gradient as it comes and DDP's buckets (laid out like the parameters) take it stride for stride.
    The oracle is autograd itself: the strides of the gradient each parameter's hook receives."""
    cfg = load_config("tiny", [f"data.root={records}", *FAST, "train.batch_size=2"])
    trainer = Trainer(cfg, tmp_path / "layout", DistInfo(0, 1, 0, torch.device("cpu")))
    received = {}
    for name, param in trainer.model.named_parameters():
        if param.requires_grad:
            param.register_hook(lambda grad, name=name: received.setdefault(name, grad.stride()) and None)
    trainer.step(next(iter(trainer.loader)))
    channels_last = [n for n, p in trainer.model.named_parameters() if p.dim() == 4 and not p.is_contiguous()]
    assert any(n.startswith("detector.backbone.bottom_up.") for n in channels_last)
    assert any(n.startswith("detector.proposal_generator.") for n in channels_last)
    params = dict(trainer.model.named_parameters())
    assert len(received) > 100
    assert {n: s for n, s in received.items() if s != params[n].stride()} == {}


@pytest.mark.parametrize("optimizer", ["adam", "muon"])
def test_non_finite_loss_skips_the_step(records, tmp_path, optimizer):
    cfg = load_config("tiny", [f"data.root={records}", *FAST, "train.batch_size=2", f"optim.name={optimizer}"])
    trainer = Trainer(cfg, tmp_path / "nan", DistInfo(0, 1, 0, torch.device("cpu")))
    batch = [trainer.loader.dataset[key] for key in next(iter(trainer.sampler))]
    bad = [replace(batch[0], views=[replace(v, K=v.K * float("nan")) for v in batch[0].views])] + batch[1:]
    before = {k: v.detach().clone() for k, v in trainer.model.named_parameters()}
    values = trainer.step(bad)
    assert values["skipped"] == 1.0 and trainer.step.skipped == 1
    assert all(torch.equal(before[k], v) for k, v in trainer.model.named_parameters())
    values = trainer.step(batch)
    assert values["skipped"] == 0.0
    assert any(not torch.equal(before[k], v) for k, v in trainer.model.named_parameters())
    assert all(p.grad is None for p in trainer.step.params)  # nothing left over for the next step
    trainer.step = lambda batch, **_: {"loss": float("nan"), "skipped": 1.0}  # from now on every step is non-finite
    # defaults: > 0.25 of 20; steps are read (and the guard counts them) at the log line
    with pytest.raises(TooManySkippedSteps, match=r"6 of the last 6 steps \(up to iteration 6\)"):
        trainer.train()
    assert trainer.iteration == cfg.train.log_every


def test_clipping_caps_the_step_and_the_log_shows_when(records, tmp_path):
    """One SGD step (no momentum or decay, one rate for every parameter) moves the weights by lr times
    the gradient, whose norm ``optim.clip_grad_norm`` caps; ``metrics.csv`` logs the norm before
    clipping (the interval's mean and its largest step) and the share of steps clipped."""
    sgd = [
        "optim.name=sgd",
        "optim.lr=1e-3",
        "optim.momentum=0",
        "optim.weight_decay=0",
        "optim.steps=[]",
        "model.shape.global_stage=0",
        "train.batch_size=2",
    ]
    moved, norms = {}, {}
    for name, clip in (("free", "0"), ("capped", None)):
        clip = clip or f"{norms['free'] / 4}"  # a quarter of the unclipped step's norm
        cfg = load_config("tiny", [f"data.root={records}", *FAST, *sgd, f"optim.clip_grad_norm={clip}"])
        trainer = Trainer(cfg, tmp_path / name, DistInfo(0, 1, 0, torch.device("cpu")))
        batch = [trainer.loader.dataset[key] for key in next(iter(trainer.sampler))]
        before = [p.detach().clone() for p in trainer.step.params]
        values = trainer.step(batch)
        moved[name] = (
            torch.cat([(p.detach() - b).flatten() for p, b in zip(trainer.step.params, before, strict=True)])
            .norm()
            .item()
        )
        norms[name] = values["grad_norm"].item()  # the step hands back 0-d tensors (no device read per step)
        assert values["clipped"] == (1.0 if name == "capped" else 0.0)
    assert norms["capped"] == pytest.approx(norms["free"], rel=1e-5)  # the same model, batch and gradient
    assert moved["free"] == pytest.approx(1e-3 * norms["free"], rel=1e-3)
    assert moved["capped"] == pytest.approx(1e-3 * norms["free"] / 4, rel=1e-3)
    assert (
        main(
            _args(
                records,
                tmp_path / "log",
                "optim.max_iter=3",
                "train.log_every=3",
                "train.batch_size=2",
                "optim.clip_grad_norm=1e-6",
                "val.period=0",
            )
        )
        == 0
    )
    (row,) = read_metrics(tmp_path / "log")
    assert row["clipped"] == 1.0 and row["grad_norm_max"] >= row["grad_norm"] > 0


def test_meter_keeps_the_largest_finite_gradient_norm_of_its_interval():
    """A spike shows in ``grad_norm_max`` whatever the mean; a skipped step's NaN or inf does not
    (``skipped`` counts it), in either order."""
    for norms in ([3.0, 400.0, float("nan"), 5.0], [float("inf"), 3.0, 400.0, 5.0]):
        meter = Meter()
        for norm in norms:  # as a step hands them in: 0-d tensors, and plain numbers from a skipped step
            meter.add({"grad_norm": torch.tensor(norm), "loss": 1.0})
        summary = meter.means()
        assert summary["grad_norm_max"] == 400.0 and summary["loss"] == 1.0
        # what metrics.csv, log.txt and TensorBoard receive: Python floats, never tensors
        assert all(type(v) is float for v in summary.values()), summary


def test_model_api_for_the_evaluator(records, tmp_path):
    assert main(_args(records, tmp_path / "api", "optim.max_iter=1", "train.batch_size=2")) == 0
    model, config = load_model(tmp_path / "api" / "checkpoints" / "model_0000001.pt")
    from usl.data import CategoryIndex, decode_frame
    from usl.records import RecordsDataset

    dataset = RecordsDataset(records, "val")
    frame = decode_frame(dataset.read_scene(dataset.scene_ids[0], views=[0])[0], CategoryIndex(dataset.categories))
    for mode in ("gt_boxes", "detections"):
        (pred,) = model.predict([frame], mode=mode)
        assert isinstance(pred, ObjectPredictions) and pred.verts.shape[1:] == (162, 3)


def test_clear_errors(records, tmp_path, capsys):
    def error_of(argv):
        assert main(argv) == 2
        return capsys.readouterr().err

    assert "missing.yaml" in error_of(["--config", str(tmp_path / "missing.yaml")])
    assert "unknown key(s) ['lrr']" in error_of(_args(records, tmp_path / "x", "optim.lrr=1"))
    assert "data.root is not set" in error_of(["--config", "tiny", "--out", str(tmp_path / "y")])
    assert "nowhere" in error_of(["--config", "tiny", "--out", str(tmp_path / "y"), "data.root=/nowhere"])
    assert "too few" in error_of(_args(records, tmp_path / "z", "train.batch_size=64"))
    assert "does not exist" in error_of(["--resume", str(tmp_path / "nothing.pt")])
    assert "--resume needs" in error_of(["--resume"])
    assert main(_args(records, tmp_path / "done", "optim.max_iter=1", "train.batch_size=2")) == 0
    assert "already holds checkpoints" in error_of(_args(records, tmp_path / "done", "optim.max_iter=1"))

    with pytest.raises(CheckpointError, match="no checkpoint in this folder"):
        load_model(tmp_path)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="garbage.pt could not be read"):
        load_model(garbage)
    foreign = tmp_path / "foreign.pt"
    torch.save({"weights": torch.zeros(1)}, foreign)
    with pytest.raises(CheckpointError, match="not a usl checkpoint"):
        load_model(foreign)
