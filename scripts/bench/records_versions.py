"""What reading older record schemas costs: row reads per CPU-second, interleaved in one process, of
the same scenes from a v1 folder read as usl 0.1 did (no upgrade), the v1 folder upgraded to v3 rows
on read, a v2 folder upgraded on read, and a v3 folder; then whole samples decoded to tensors from
the v3 folder.

    python scripts/bench/records_versions.py V1_ROOT V2_ROOT V3_ROOT   # one dataset in each schema
"""

import argparse
import random
import time
from bisect import bisect_right

from usl.data import CategoryIndex, decode_frame
from usl.records import RecordsDataset


def base_read(shard, first, offsets):  # usl 0.1's read_rows: no upgrade step
    rows = [first + o for o in offsets]
    g0 = bisect_right(shard.group_starts, min(rows)) - 1
    g1 = bisect_right(shard.group_starts, max(rows)) - 1
    t = shard.file.read_row_groups(list(range(g0, g1 + 1)))
    return t.take([r - int(shard.group_starts[g0]) for r in rows]).to_pylist()


parser = argparse.ArgumentParser(
    description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
)
parser.add_argument("v1_root", help="a schema-v1 dataset folder")
parser.add_argument("v2_root", help="the same scenes in schema v2")
parser.add_argument("v3_root", help="the same scenes in schema v3 (e.g. a migrated copy)")
args = parser.parse_args()
v1, v2, v3 = (RecordsDataset(root, "train") for root in (args.v1_root, args.v2_root, args.v3_root))
rng = random.Random(0)
picks = [(s, sorted(rng.sample(range(v1.num_views(s)), 5))) for s in rng.choices(v1.scene_ids, k=200)]


def v1_base(s, views):
    loc = v1._location(s)
    return base_read(v1._shard(loc.shard, "frames"), loc.first_row, views)


cases = {
    "v1, read as usl 0.1 did": v1_base,
    "v1, upgraded to v3 rows": v1.read_scene,
    "v2, upgraded to v3 rows": v2.read_scene,
    "v3": v3.read_scene,
}
cpu = dict.fromkeys(cases, 0.0)
for _ in range(5):
    for name, read in cases.items():
        c = time.process_time()
        for s, views in picks:
            read(s, views)
        cpu[name] += time.process_time() - c
for name, t in cpu.items():
    print(f"{name:26s} {5 * len(picks) / t:8.1f} five-view reads per CPU-second (rows only, no decoding)")
cats = CategoryIndex(v3.categories)
for name, ds in (("v2", v2), ("v3", v3)):
    c = time.process_time()
    for s, views in picks[:100]:
        [decode_frame(r, cats, with_depth=True) for r in ds.read_scene(s, views)]
    print(
        f"{name} with decode_frame      {100 / (time.process_time() - c):8.1f} five-view samples per CPU-second (depth too)"
    )
