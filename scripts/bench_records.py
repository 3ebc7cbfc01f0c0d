"""Reader throughput: random 5-view samples per second per core, as a training DataLoader reads them.

A sample = one scene's 5 views read by random access (row groups of that scene only), with
images, masks and boxes decoded to tensors (usl.data.decode_frame). Measured in one process (one
core) and with 2 DataLoader workers side by side, so the per-core figure and scaling print together.

    python scripts/bench_records.py --root data/scene_shapes_small --split train
"""
from __future__ import annotations

import argparse
import random
import time

import torch
from torch.utils.data import DataLoader, Dataset

from usl.data import CategoryIndex, decode_frame
from usl.records import RecordsDataset

VIEWS_PER_SAMPLE = 5


class FiveViewSamples(Dataset):
    def __init__(self, root: str, split: str, num_samples: int, seed: int = 0):
        self.records = RecordsDataset(root, split)
        self.categories = CategoryIndex(self.records.categories)
        rng = random.Random(seed)
        self.picks = []
        for _ in range(num_samples):
            scene = rng.choice(self.records.scene_ids)
            n = self.records.num_views(scene)
            self.picks.append((scene, sorted(rng.sample(range(n), min(VIEWS_PER_SAMPLE, n)))))

    def __len__(self) -> int:
        return len(self.picks)

    def __getitem__(self, i: int) -> int:
        scene, views = self.picks[i]
        frames = [decode_frame(row, self.categories) for row in self.records.read_scene(scene, views)]
        return sum(int(f.masks.shape[0]) for f in frames)


def measure(dataset: Dataset, workers: int) -> float:
    loader = DataLoader(dataset, batch_size=None, num_workers=workers, shuffle=False)
    start = time.perf_counter()
    for _ in loader:
        pass
    return len(dataset) / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--root", required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--samples", type=int, default=200)
    args = parser.parse_args()
    torch.set_num_threads(1)
    dataset = FiveViewSamples(args.root, args.split, args.samples)
    row = dataset.records.read_scene(dataset.picks[0][0], [0])[0]
    print(f"dataset {args.root} [{args.split}]: {len(dataset.records)} scenes, images {row['width']}x{row['height']}")
    one = measure(dataset, 0)
    two = measure(dataset, 2)
    print(f"1 process : {one:7.1f} five-view samples/s  -> {one:7.1f} per core (target >= 40)")
    print(f"2 workers : {two:7.1f} five-view samples/s  -> {two / 2:7.1f} per core; scaling x{two / one:.2f}")


if __name__ == "__main__":
    main()
