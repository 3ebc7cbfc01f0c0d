"""Dataset folders of older record schemas (v1 as usl 0.1 wrote them, v2 as usl wrote them before
depth became an Image struct), made from a current build for reading/migration tests.

Independent of usl's upgrade code: rows are turned back by hand (depth bytes; for v1 also image
bytes, ``bbox``) and written with that version's schema, row groups as in the source, plus that
version's manifest (and, for v2, dataset card).
"""

import json
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from usl.records.schema import HF_METADATA_KEY, METADATA_KEY, hf_features, table_schema
from usl.records.shards import sha256_file


def _old_row(row, table, version):
    if table == "objects":
        return row
    row = {**row, "depth": None if row["depth"] is None else row["depth"]["bytes"]}
    if version == 2:
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


def write_old_file(source: Path, target: Path, table: str, version: int) -> dict:
    """One current shard file rewritten in schema ``version`` at ``target``; its size and checksum."""
    source = pq.ParquetFile(source)
    meta = json.loads(source.schema_arrow.metadata[METADATA_KEY])
    metadata = {METADATA_KEY: json.dumps({**meta, "schema_version": version})}
    if version == 2:
        metadata[HF_METADATA_KEY] = json.dumps({"info": {"features": hf_features(table, 2)}})
    schema = table_schema(table, version).with_metadata(metadata)
    target.parent.mkdir(parents=True, exist_ok=True)
    with pq.ParquetWriter(target, schema) as writer:
        for group in range(source.num_row_groups):
            rows = [_old_row(r, table, version) for r in source.read_row_group(group).to_pylist()]
            writer.write_table(pa.Table.from_pylist(rows, schema=schema))
    return {"bytes": target.stat().st_size, "sha256": sha256_file(target)}


def write_old_copy(root: Path, target: Path, version: int) -> Path:
    """``root`` (a current build) rewritten as a schema ``version`` (1 or 2) folder at ``target``."""
    manifest = json.loads((root / "manifest.json").read_text())
    manifest["schema_version"] = version
    for split, entry in manifest["splits"].items():
        for shard in entry["shards"]:
            for table in ("frames", "objects"):
                if not shard[table]:
                    continue
                file = f"{split}/{table}-{shard['index']:05d}.parquet" if version == 1 else shard[table]["file"]
                written = write_old_file(root / shard[table]["file"], target / file, table, version)
                shard[table] = {"file": file, "rows": shard[table]["rows"], **written}
    if version == 2:  # a card of its own schema, which migrating must write anew
        card = (root / "README.md").read_text()
        old_card = card.replace("record schema version 3", "record schema version 2")
        assert old_card != card
        (target / "README.md").write_text(old_card)
    (target / "manifest.json").write_text(json.dumps(manifest, indent=1))
    return target
