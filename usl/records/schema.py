"""Arrow schemas built from ``data_specs/schema_v*.yaml`` (the single source of the record layout)."""

from __future__ import annotations

import json
from functools import cache
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from data_specs import load_schema_spec
from usl.errors import UslError, one_line

SCHEMA_VERSION = 3  # what writers produce; readers also read every version in KNOWN_VERSIONS
KNOWN_VERSIONS = (1, 2, 3)
METADATA_KEY = b"usl"
HF_METADATA_KEY = b"huggingface"  # Hugging Face datasets reads its features from here
DOC_KEY = b"doc"

_SCALARS = {
    "string": pa.string(),
    "binary": pa.binary(),
    "int32": pa.int32(),
    "int64": pa.int64(),
    "float32": pa.float32(),
    "float64": pa.float64(),
    # Hugging Face's Image feature, with the Arrow type `datasets` gives it.
    "image": pa.struct([pa.field("bytes", pa.binary()), pa.field("path", pa.string())]),
}


def _arrow_type(spec: Any, all_nullable: bool) -> pa.DataType:
    if isinstance(spec, str):
        return _SCALARS[spec]
    if "list" in spec:
        item = _arrow_type(spec["list"], all_nullable)
        return pa.list_(item, spec["size"]) if "size" in spec else pa.list_(item)
    if "struct" in spec:
        return pa.struct([_arrow_field(f, all_nullable) for f in spec["struct"]])
    raise ValueError(f"unknown type spec {spec!r} in the record schema")


def _arrow_field(spec: dict[str, Any], all_nullable: bool) -> pa.Field:
    nullable = all_nullable or bool(spec.get("nullable", False))
    metadata = {DOC_KEY: spec["doc"].encode()} if "doc" in spec else None
    return pa.field(spec["name"], _arrow_type(spec["type"], all_nullable), nullable=nullable, metadata=metadata)


@cache
def table_schema(table: str, version: int = SCHEMA_VERSION) -> pa.Schema:
    """Arrow schema of ``frames`` or ``objects`` (field docs as field metadata, no dataset metadata).

    From v2 on every Arrow field is nullable: Hugging Face datasets ignores its features for a
    non-nullable field. Which fields are required is the spec's business (``required_fields``).
    """
    spec = load_schema_spec(version)["tables"][table]
    return pa.schema([_arrow_field(f, version >= 2) for f in spec["fields"]])


def required_fields(table: str, version: int = SCHEMA_VERSION) -> list[str]:
    """Top-level fields that must never be null."""
    return [f["name"] for f in load_schema_spec(version)["tables"][table]["fields"] if not f.get("nullable", False)]


def shard_file(table: str, split: str, index: int) -> str:
    """Where a shard of ``table`` lives, relative to the dataset root (the path manifest.json lists)."""
    return load_schema_spec(SCHEMA_VERSION)["shard_path"].format(table=table, split=split, index=index)


def _hf_feature(spec: Any) -> Any:
    """A field type as Hugging Face ``Features.to_dict`` writes it, in the forms every datasets
    release since 2.x reads: ``Sequence`` with ``length`` for fixed lists, ``[feature]`` for lists."""
    if spec == "image":
        return {"_type": "Image"}
    if isinstance(spec, str):
        return {"dtype": spec, "_type": "Value"}
    if "list" in spec:
        item = _hf_feature(spec["list"])
        return {"feature": item, "length": spec["size"], "_type": "Sequence"} if "size" in spec else [item]
    return {f["name"]: _hf_feature(f["type"]) for f in spec["struct"]}


def hf_features(table: str, version: int = SCHEMA_VERSION) -> dict[str, Any]:
    """Hugging Face features of a table (v2 on): images, and from v3 depth, decode to PIL;
    ``category_id`` stays the dataset's id."""
    return {f["name"]: _hf_feature(f["type"]) for f in load_schema_spec(version)["tables"][table]["fields"]}


def legacy_hf_features(table: str, categories: list[dict[str, Any]]) -> dict[str, Any]:
    """The features earlier v2 builds wrote: ``category_id`` a ClassLabel indexed by the dataset's id,
    ``__unused_<id>__`` at the ids no category has. Same Arrow data; kept so those datasets validate."""
    by_id = {int(c["id"]): str(c["name"]) for c in categories}
    names = [by_id.get(i, f"__unused_{i}__") for i in range(max(by_id, default=-1) + 1)]

    def swap(feature: Any, name: str = "") -> Any:
        if name == "category_id":
            return {"names": names, "_type": "ClassLabel"}
        if isinstance(feature, list):
            return [swap(feature[0])]
        if isinstance(feature, dict) and "_type" not in feature:
            return {k: swap(v, k) for k, v in feature.items()}
        return feature

    return swap(hf_features(table, 2))


def dataset_schema(table: str, metadata: dict[str, Any]) -> pa.Schema:
    """The schema a shard of ``table`` is written with: dataset metadata under ``usl`` (name, schema
    version, categories, layout) and the Hugging Face features under ``huggingface``."""
    features = {"info": {"features": hf_features(table)}}
    return table_schema(table).with_metadata(
        {
            METADATA_KEY: json.dumps(metadata, sort_keys=True).encode(),
            HF_METADATA_KEY: json.dumps(features).encode(),
        }
    )


def read_metadata(schema: pa.Schema, path: str) -> dict[str, Any]:
    """Dataset metadata of a shard; refuses unknown schema versions with a clear message."""
    raw = (schema.metadata or {}).get(METADATA_KEY)
    if raw is None:
        raise UslError(f"{path}: not a usl record shard (no '{METADATA_KEY.decode()}' schema metadata)")
    meta = json.loads(raw)
    check_version(meta.get("schema_version"), path)
    return meta


def file_schema_version(path: Path) -> int:
    """The record schema version a shard file was written in (read from its footer only)."""
    try:
        schema = pq.read_schema(path)
    except Exception as exc:  # pyarrow raises several types for broken footers
        raise UslError(f"{path}: unreadable Parquet footer ({one_line(exc)})") from exc
    return read_metadata(schema, str(path))["schema_version"]


def check_version(version: Any, path: str) -> None:
    if version not in KNOWN_VERSIONS:
        raise UslError(
            f"{path}: record schema version {version!r} is not known to this usl "
            f"(known: {', '.join(map(str, KNOWN_VERSIONS))}); upgrade usl or rebuild the dataset"
        )
