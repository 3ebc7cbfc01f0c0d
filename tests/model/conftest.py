import sys
from pathlib import Path

import pytest
import torch

# Lets the model tests import their shared helpers (detection_oracles.py, detection_scenes.py) by module name.
sys.path.insert(0, str(Path(__file__).parent))


@pytest.fixture(autouse=True)
def one_torch_thread():
    """These tests use small tensors that gain nothing from threads, and oversubscribed
    cores (pytest -n, busy CI hosts) make spinning intra-op threads crawl."""
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(previous)
