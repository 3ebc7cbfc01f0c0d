"""Parameter groups of the model's learning-rate factors, and the schedule over them."""

import pytest
import torch
from torch import nn

from usl.config import load_config
from usl.engine.config import OptimConfig
from usl.engine.optim import build_optimizer, build_scheduler, lay_out_state_like_params
from usl.model.usl_model import USLModel


def _net() -> nn.Module:
    net = nn.Module()
    net.backbone = nn.Linear(2, 2)
    net.head = nn.Module()
    net.head.stage = nn.Linear(2, 2)
    net.head.out = nn.Linear(2, 1)
    net.frozen = nn.Linear(2, 2).requires_grad_(False)
    return net


def _rates(optimizer: torch.optim.Optimizer, net: nn.Module) -> dict[str, float]:
    rate = {id(p): g["lr"] for g in optimizer.param_groups for p in g["params"]}
    return {name: rate[id(p)] for name, p in net.named_parameters() if p.requires_grad}


def test_longest_prefix_sets_each_parameters_rate_and_the_schedule_scales_all():
    net = _net()
    cfg = OptimConfig(name="adam", lr=1e-3, steps=(2,), gamma=0.1)
    optimizer = build_optimizer(net.named_parameters(), cfg, {"head": 10.0, "head.out": 2.0})
    expected = {"backbone": 1e-3, "head.stage": 1e-2, "head.out": 2e-3}
    rates = _rates(optimizer, net)
    assert set(rates) == {f"{m}.{k}" for m in expected for k in ("weight", "bias")}  # frozen ones left out
    assert all(rates[name] == pytest.approx(expected[name.rsplit(".", 1)[0]]) for name in rates)
    scheduler = build_scheduler(optimizer, cfg)
    for _ in range(2):
        optimizer.step()
        scheduler.step()
    assert all(r == pytest.approx(0.1 * expected[n.rsplit(".", 1)[0]]) for n, r in _rates(optimizer, net).items())


def test_a_factor_naming_no_parameter_is_an_error_naming_it():
    with pytest.raises(ValueError, match="headx"):
        build_optimizer(_net().named_parameters(), OptimConfig(), {"headx": 2.0})  # a prefix, not a word part


MODEL = [
    "model.categories=[a, b]",
    *(f"model.layout_range.{k}={v}" for k, v in zip(("z0", "z1", "rho0", "rho1"), (1, 9, 0.1, 2), strict=True)),
]


def test_the_global_shape_stage_learns_at_a_tenth_of_the_rate():
    """The model names its own factors; the global stage's 0.1 is what kept its tanh from saturating."""
    cfg = load_config("tiny", MODEL)
    model = USLModel(cfg.model, cfg.loss, load_init_weights=False)
    rates = _rates(build_optimizer(model.named_parameters(), cfg.optim, model.lr_factors()), model)
    slow = {name for name, rate in rates.items() if rate == pytest.approx(0.1 * cfg.optim.lr)}
    assert slow and slow == {name for name in rates if name.startswith("shape_head.global_mlp.")}
    assert all(rates[name] == cfg.optim.lr for name in rates.keys() - slow)
    cfg = load_config("tiny", [*MODEL, "model.shape.global_stage=0"])
    assert USLModel(cfg.model, cfg.loss, load_init_weights=False).lr_factors() == {}


@pytest.mark.parametrize("name", ["adam", "sgd", "muon"])  # muon: the weight is an output layer's, Adam's
def test_loaded_state_takes_its_parameters_layout_so_the_fused_step_pairs_the_right_elements(name):
    """A channels-last weight resumed from a checkpoint whose state is NCHW (written before its weights
    were channels-last, or on CUDA): after ``lay_out_state_like_params`` the fused step equals the
    per-element (foreach) step on NCHW tensors. Without it the fused kernel pairs other elements."""
    torch.manual_seed(0)
    weight, grad = torch.randn(4, 3, 3, 3), torch.randn(4, 3, 3, 3)
    cfg = OptimConfig(name=name, lr=0.1, momentum=0.9, weight_decay=0.0)

    def stepped_twice(fused_layout: bool) -> torch.Tensor:
        layout = torch.channels_last if fused_layout else torch.contiguous_format
        param = nn.Parameter(weight.clone().contiguous(memory_format=layout))
        if fused_layout:
            optimizer = build_optimizer([("w", param)], cfg)
        else:
            kind = torch.optim.SGD if name == "sgd" else torch.optim.Adam
            optimizer = kind([param], lr=0.1, **({"momentum": 0.9} if name == "sgd" else {}), foreach=True)
        param.grad = grad.clone().contiguous(memory_format=layout)
        optimizer.step()
        saved = optimizer.state_dict()
        for state in saved["state"].values():  # as a checkpoint written with NCHW weights holds it
            state.update({k: v.contiguous() for k, v in state.items() if v.dim() == 4})
        optimizer.load_state_dict(saved)
        if fused_layout:
            lay_out_state_like_params(optimizer)
            assert all(v.stride() == param.stride() for v in optimizer.state[param].values() if v.dim() == 4)
        param.grad = (2 * grad).contiguous(memory_format=layout)
        optimizer.step()
        return param.detach()

    torch.testing.assert_close(stepped_twice(True), stepped_twice(False))
