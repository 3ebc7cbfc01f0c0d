"""Muon for hidden weights, Adam for the rest: against torch's own Muon and Adam, the SVD, and resumption."""

import os
import socket
from pathlib import Path

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp
from torch import nn

from tests.engine.test_optim import MODEL
from usl.config import load_config
from usl.engine import muon as muon_module
from usl.engine.config import OptimConfig
from usl.engine.muon import MuonAdam, is_hidden_weight, orthogonalize
from usl.engine.optim import build_optimizer
from usl.model.usl_model import USLModel


def test_newton_schulz_gives_the_svds_orthogonal_factor_up_to_its_loose_singular_values():
    """The quintic trades exactness for speed: singular values land in about (0.5, 1.5), and the
    singular vectors are the SVD's (the result is close to U V^T in direction)."""
    torch.manual_seed(0)
    matrices = torch.randn(3, 24, 80) * torch.logspace(-2, 1, 80)  # ill-conditioned, wide
    for batch in (matrices, matrices.mT):  # and tall
        ortho = orthogonalize(batch)
        assert ortho.shape == batch.shape
        sigma = torch.linalg.svdvals(ortho)
        assert sigma.min() > 0.5 and sigma.max() < 1.5
        u, _, vh = torch.linalg.svd(batch, full_matrices=False)
        exact = u @ vh
        cosine = (ortho * exact).sum((-2, -1)) / (ortho.norm(dim=(-2, -1)) * exact.norm(dim=(-2, -1)))
        assert (cosine > 0.95).all()


def _params(shapes, seed=0, channels_last=False):
    torch.manual_seed(seed)
    layout = torch.channels_last if channels_last else torch.contiguous_format
    return [
        nn.Parameter(
            (torch.randn(shape) * 0.1).contiguous(memory_format=layout if len(shape) == 4 else torch.contiguous_format)
        )
        for shape in shapes
    ]


def _steps(optimizer, params, grads):
    for grad in grads:
        for param, g in zip(params, grad, strict=True):
            param.grad = g.clone()
        optimizer.step()


def test_muon_groups_equal_torch_muon_and_convolutions_step_as_out_by_in_kh_kw_matrices():
    """torch.optim.Muon (2-D only, orthogonalising in bfloat16) with Adam's RMS matching and no decay
    is the oracle; a convolution's weight equals a matrix (out, in x kh x kw) stepped by it."""
    shapes = [(32, 16, 3, 3), (32, 16, 3, 3), (64, 35), (20, 90)]  # two of one shape: orthogonalised together
    ours = _params(shapes)
    theirs = [nn.Parameter(p.detach().reshape(p.shape[0], -1).clone()) for p in ours]
    torch.manual_seed(1)
    grads = [[torch.randn(s) for s in shapes] for _ in range(4)]
    _steps(MuonAdam([{"params": ours, "muon": True}], lr=0.02, momentum=0.95), ours, grads)
    oracle = torch.optim.Muon(theirs, lr=0.02, weight_decay=0.0, momentum=0.95, adjust_lr_fn="match_rms_adamw")
    _steps(oracle, theirs, [[g.reshape(g.shape[0], -1) for g in grad] for grad in grads])
    for mine, ref, start in zip(ours, theirs, _params(shapes), strict=True):
        moved, ref_moved = (
            (mine.detach() - start.detach()).reshape(ref.shape),
            ref.detach() - start.detach().reshape(ref.shape),
        )
        assert moved.norm() > 0.01
        torch.testing.assert_close(moved, ref_moved, rtol=0, atol=0.02 * ref_moved.abs().max().item())


def test_adam_groups_equal_torch_adam():
    shapes = [(32,), (3, 67), (16, 3, 7, 7)]
    ours, theirs = _params(shapes), _params(shapes)
    torch.manual_seed(1)
    grads = [[torch.randn(s) for s in shapes] for _ in range(5)]
    _steps(MuonAdam([{"params": ours}], lr=1e-3), ours, grads)
    _steps(torch.optim.Adam(theirs, lr=1e-3, foreach=False), theirs, grads)
    for mine, ref in zip(ours, theirs, strict=True):
        torch.testing.assert_close(mine.detach(), ref.detach())


def test_a_step_flagged_non_finite_moves_no_parameter_and_no_state():
    """GradScaler hands ``found_inf`` over on the device; the step then changes nothing (no host read)."""
    shapes = [(32, 16, 3, 3), (64, 35), (3, 67), (32,)]
    params = _params(shapes)
    optimizer = MuonAdam([{"params": params[:2], "muon": True}, {"params": params[2:]}], lr=1e-2)
    _steps(optimizer, params, [[torch.randn(s) for s in shapes]])
    before = [p.detach().clone() for p in params]
    state = {k: v.clone() for p in params for k, v in optimizer.state[p].items()}
    for param in params:
        param.grad = torch.full_like(param, float("nan"))
    scaler = torch.amp.GradScaler("cpu", init_scale=1.0)
    scaler.scale(torch.ones(()))  # as the training step does
    scaler.step(optimizer)
    assert all(torch.equal(b, p) for b, p in zip(before, params, strict=True))
    after = {k: v for p in params for k, v in optimizer.state[p].items()}
    assert all(torch.equal(state[k], after[k]) for k in state)


def test_a_resumed_optimizer_steps_as_the_one_that_never_stopped():
    shapes = [(32, 16, 3, 3), (64, 35), (3, 67), (32,)]
    torch.manual_seed(1)
    grads = [[torch.randn(s) for s in shapes] for _ in range(4)]

    def optimizer_for(params):
        return MuonAdam([{"params": params[:2], "muon": True}, {"params": params[2:]}], lr=1e-2)

    straight = _params(shapes)
    _steps(optimizer_for(straight), straight, grads)
    resumed = _params(shapes)
    first = optimizer_for(resumed)
    _steps(first, resumed, grads[:2])
    second = optimizer_for(resumed)
    second.load_state_dict(first.state_dict())
    _steps(second, resumed, grads[2:])
    for a, b in zip(straight, resumed, strict=True):
        torch.testing.assert_close(a.detach(), b.detach(), rtol=0, atol=0)


def test_muon_takes_the_hidden_weights_and_adam_the_stem_the_outputs_and_the_vertex_offsets():
    cfg = load_config("tiny", [*MODEL, "optim.name=muon"])
    model = USLModel(cfg.model, cfg.loss, load_init_weights=False)
    optimizer = build_optimizer(model.named_parameters(), cfg.optim, model.lr_factors(), model.prediction_weights())
    muon = {id(p) for g in optimizer.param_groups if g["muon"] for p in g["params"]}
    names = {name for name, p in model.named_parameters() if id(p) in muon}
    assert "detector.backbone.bottom_up.layer1.0.conv1.weight" in names  # a convolution
    assert "shape_head.stages.0.gconvs.0.w0.weight" in names and "shape_head.global_mlp.0.weight" in names
    assert "detector.backbone.bottom_up.conv1.weight" not in names  # the stem
    assert not any(
        n.endswith(("cls_score.weight", "bbox_pred.weight", "z_pred.weight", "offset.weight")) for n in names
    )
    assert "shape_head.global_mlp.4.weight" not in names and model.prediction_weights() == {
        "shape_head.global_mlp.4.weight"
    }
    assert all(p.ndim >= 2 and is_hidden_weight(p) for n, p in model.named_parameters() if n in names)
    rates = {g["lr"] for g in optimizer.param_groups if g["muon"]}
    assert rates == {cfg.optim.lr, 0.1 * cfg.optim.lr}  # the global stage keeps its own rate under Muon too


def test_muon_refuses_weight_decay_and_bias_shaped_parameters():
    with pytest.raises(ValueError, match="muon has no weight decay"):
        OptimConfig(name="muon", weight_decay=1e-4)
    with pytest.raises(ValueError, match=r"shape \(8,\) is not one"):
        MuonAdam([{"params": [nn.Parameter(torch.zeros(8))], "muon": True}], lr=1e-3)


SHARED_SHAPES = [(32, 16, 3, 3), (32, 16, 3, 3), (64, 35), (128, 288), (20, 90), (3, 67), (32,)]


def _sharded_rank(rank: int, port: int, out: str) -> None:
    """Both processes step the same replicas (as DDP's all-reduced gradients make them)."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port))
    dist.init_process_group("gloo", rank=rank, world_size=2)
    try:
        calls = []
        original = muon_module.orthogonalize
        muon_module.orthogonalize = lambda matrices: calls.append(tuple(matrices.shape)) or original(matrices)
        params = _params(SHARED_SHAPES, channels_last=True)  # as the backbone's weights are on the CPU
        optimizer = MuonAdam([{"params": params[:5], "muon": True}, {"params": params[5:]}], lr=1e-2)
        torch.manual_seed(1)
        grads = [[torch.randn(s) for s in SHARED_SHAPES] for _ in range(3)]
        # the gradients in their weights' layout, as autograd gives them
        _steps(
            optimizer, params, [[torch.empty_like(p).copy_(g) for g, p in zip(gs, params, strict=True)] for gs in grads]
        )
        torch.save({"params": [p.detach() for p in params], "calls": calls}, Path(out, f"{rank}.pt"))
    finally:
        dist.destroy_process_group()


def test_under_ddp_each_process_orthogonalises_a_share_and_all_step_as_one_process_does(tmp_path):
    with socket.socket() as s:  # a free port
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    mp.start_processes(_sharded_rank, args=(port, str(tmp_path)), nprocs=2, start_method="spawn")
    ranks = [torch.load(tmp_path / f"{rank}.pt") for rank in range(2)]
    alone = _params(SHARED_SHAPES)
    torch.manual_seed(1)
    optimizer = MuonAdam([{"params": alone[:5], "muon": True}, {"params": alone[5:]}], lr=1e-2)
    _steps(optimizer, alone, [[torch.randn(s) for s in SHARED_SHAPES] for _ in range(3)])
    for rank in ranks:
        for mine, ref in zip(rank["params"], alone, strict=True):
            assert torch.equal(mine, ref.detach())
    calls = [sorted(set(rank["calls"])) for rank in ranks]
    assert calls[0] and calls[1] and not set(calls[0]) & set(calls[1])  # disjoint shares, none idle
    assert sorted(calls[0] + calls[1]) == [(1, 20, 90), (1, 64, 35), (1, 128, 288), (2, 32, 144)]
