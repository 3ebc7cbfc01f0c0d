"""Fixtures shared by every test folder."""

import os
from pathlib import Path

import pytest
import torch

from pipelines.scene_shapes.render import load_triton_before_mesa
from tests.data.synthetic_records import build_synthetic_records
from tests.faults.tally import pytest_sessionfinish, pytest_terminal_summary, pytest_testnodedown  # noqa: F401


def pytest_configure(config):
    """Tests render with pyrender (oracles, Scene-Shapes builds) and train in the same worker
    process: with a CUDA build of torch, triton must be loaded before Mesa's EGL (see
    ``load_triton_before_mesa``), or the first test that reaches ``torch._dynamo`` after a rendering
    test crashes its worker."""
    load_triton_before_mesa()


@pytest.fixture(autouse=True)
def single_thread():
    """One intra-op thread: tests use small tensors that gain nothing from threads, and on an
    oversubscribed machine (pytest -n, busy CI hosts) spinning thread pools make them crawl."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)


@pytest.fixture(scope="session")
def synthetic_root(tmp_path_factory):
    """Records of four train scenes and one val scene of two cuboids, six views each, 64 x 64."""
    return build_synthetic_records(tmp_path_factory.mktemp("synthetic") / "records")


@pytest.fixture(scope="session")
def detectron2_weights(tmp_path_factory):
    """Seeded random weights of detectron2's PointRend and Mask R-CNN R50-FPN in the model zoo's layout
    (240 MB each: written once per session): ``{model: (path, checksum)}``."""
    from tests.model.detectron2_fixtures import MASK_RCNN, ORACLE_SEED, POINTREND, checksum, write_random_checkpoint

    folder = tmp_path_factory.mktemp("detectron2_weights")
    written = {}
    for model in (POINTREND, MASK_RCNN):
        path = folder / f"{model}.pkl"
        written[model] = (path, checksum(write_random_checkpoint(path, model, ORACLE_SEED)))
    return written


@pytest.fixture(scope="module")
def local_ray():
    """A local two-CPU Ray instance whose workers import the test helpers (tests.*) from the repository root."""
    ray = pytest.importorskip("ray")
    path = os.pathsep.join([str(Path(__file__).parents[1]), os.environ.get("PYTHONPATH", "")])
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        runtime_env={"env_vars": {"PYTHONPATH": path, "OMP_NUM_THREADS": "1"}},
    )
    yield
    ray.shutdown()
