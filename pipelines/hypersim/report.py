"""The final summary of a conversion: per split scenes, views and instances, skips by reason."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import Any

import pyarrow.compute as pc
import pyarrow.parquet as pq


def count_instances(frames_file: Path) -> int:
    """Instances in one frames shard, reading only the instance-id leaf column."""
    file = pq.ParquetFile(frames_file)
    leaf = next(
        path
        for path in (file.schema.column(i).path for i in range(len(file.schema)))
        if path.startswith("instances.") and path.endswith(".instance_id")
    )
    table = file.read(columns=[leaf])
    return int(pc.sum(pc.list_value_length(table.column("instances"))).as_py() or 0)


def describe_dataset(root: Path, manifest: dict[str, Any]) -> str:
    lines = []
    for split, entry in manifest["splits"].items():
        instances = sum(count_instances(Path(root) / s["frames"]["file"]) for s in entry["shards"])
        lines.append(
            f"  {split}: {entry['num_scenes']} trajectories, {entry['num_frames']} views, {instances} instances"
        )
    reasons: Counter = Counter()
    for skip in manifest["skips"]:
        reasons[skip["reason"]] += skip["count"]
    lines.append(f"  skipped: {sum(reasons.values())}" + ("" if reasons else " (nothing)"))
    lines += [f"    {count:8d}  {reason}" for reason, count in reasons.most_common()]
    return "\n".join(lines)
