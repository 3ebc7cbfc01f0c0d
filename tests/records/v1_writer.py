"""Schema v1 dataset folders as usl 0.1 wrote them, made from a v2 folder for reading/migration tests.

Independent of usl's upgrade code: rows are turned back by hand (image bytes, ``bbox``, int32
categories) and written with the v1 schema, row groups as in the source, plus a v1 manifest.
"""

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from usl.records.schema import METADATA_KEY, table_schema
from usl.records.shards import sha256_file


def _v1_row(row, table):
    if table == "objects":
        return row
    instances = [
        {
            "instance_id": i["instance_id"],
            "category_id": i["category_id"],
            "mask": i["mask"],
            "bbox": i["box_xyxy"],
            "area": i["area"],
            "depth_min": i["depth_min"],
        }
        for i in row["instances"]
    ]
    return {**row, "image": row["image"]["bytes"], "instances": instances}


def write_v1_copy(v2_root: Path, target: Path) -> Path:
    manifest = json.loads((v2_root / "manifest.json").read_text())
    manifest["schema_version"] = 1
    for split, entry in manifest["splits"].items():
        for shard in entry["shards"]:
            for table in ("frames", "objects"):
                if not shard[table]:
                    continue
                source = pq.ParquetFile(v2_root / shard[table]["file"])
                meta = json.loads(source.schema_arrow.metadata[METADATA_KEY])
                schema = table_schema(table, 1).with_metadata({METADATA_KEY: json.dumps({**meta, "schema_version": 1})})
                file = f"{split}/{table}-{shard['index']:05d}.parquet"
                (target / split).mkdir(parents=True, exist_ok=True)
                with pq.ParquetWriter(target / file, schema) as writer:
                    for group in range(source.num_row_groups):
                        rows = [_v1_row(r, table) for r in source.read_row_group(group).to_pylist()]
                        writer.write_table(pa.Table.from_pylist(rows, schema=schema))
                shard[table] = {
                    "file": file,
                    "rows": shard[table]["rows"],
                    "bytes": (target / file).stat().st_size,
                    "sha256": sha256_file(target / file),
                }
    (target / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return target
