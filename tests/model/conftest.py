"""Shared fixtures of the model tests: the tiny recipe on the synthetic Scene-Shapes records."""

import pytest

from usl.config import load_config
from usl.data import CategoryIndex, MultiViewDataset
from usl.model.config import LayoutRange
from usl.records import RecordsDataset


@pytest.fixture(scope="module")
def tiny_synthetic(synthetic_root):
    """(cfg, records, dataset): 4-view samples at the stored image size, categories and layout
    ranges from the records, as usl.engine.train fills them. No mirroring: the tests compare samples
    with the records' own (unreflected) geometry."""
    cfg = load_config(
        "tiny", [f"data.root={synthetic_root}", "data.num_views=4", "data.max_size=0", "data.flip_prob=0"]
    )
    records = RecordsDataset(synthetic_root, "train")
    cfg.model.categories = tuple(c["name"] for c in records.categories)
    cfg.model.layout_range = LayoutRange(**records.manifest["layout"])
    dataset = MultiViewDataset(records, cfg.data, CategoryIndex(records.categories), seed=0)
    return cfg, records, dataset
