"""Fixtures shared by every test folder."""

import pytest
import torch

from tests.data.synthetic_records import build_synthetic_records


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
