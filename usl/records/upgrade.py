"""Tables of older record schemas as the current one, converted column by column in Arrow.

The reader, the validator and ``usl-records migrate`` all go through ``upgrade_table``, so an old
dataset reads exactly like its migrated copy. One step per version, applied in turn:

* v1 -> v2: ``image`` bytes become the Image struct ``{bytes, path: null}``; instance ``bbox`` is
  renamed ``box_xyxy``; ``category_id`` widens to int64; every field becomes nullable (see
  ``schema.table_schema``).
* v2 -> v3: ``depth`` bytes become the Image struct too: the same PNG bytes, so every depth value is
  unchanged, and a null depth stays null.
"""

from __future__ import annotations

import pyarrow as pa

from .schema import KNOWN_VERSIONS, SCHEMA_VERSION, table_schema

RENAMED_INSTANCE_FIELDS = {"bbox": "box_xyxy"}
# Frames fields that go from encoded bytes to Hugging Face's Image struct in the step from version v.
TO_IMAGE_STRUCT = {1: ("image",), 2: ("depth",)}


def _image_struct(chunk: pa.Array, type_: pa.StructType) -> pa.Array:
    mask = chunk.is_null() if chunk.null_count else None
    return pa.StructArray.from_arrays([chunk, pa.nulls(len(chunk), pa.string())], fields=list(type_), mask=mask)


def _renamed_instances(chunk: pa.ListArray) -> pa.Array:
    """Rename struct fields by position; a cast alone would match by name and null them."""
    values = chunk.values
    names = [RENAMED_INSTANCE_FIELDS.get(f.name, f.name) for f in values.type]
    struct = pa.StructArray.from_arrays(values.flatten(), names=names)
    mask = chunk.is_null() if chunk.null_count else None
    return pa.ListArray.from_arrays(chunk.offsets, struct, mask=mask)


def _step(table: pa.Table, name: str, version: int) -> pa.Table:
    """The columns of a ``version`` table in schema ``version + 1``."""
    target = table_schema(name, version + 1)
    fields, columns = [], []
    for field, column in zip(table.schema, table.columns, strict=True):
        new = target.field(field.name)
        if column.num_chunks == 0:  # an empty read has no chunks to convert
            column = pa.chunked_array([pa.array([], field.type)])
        if name == "frames" and field.name in TO_IMAGE_STRUCT.get(version, ()):
            column = pa.chunked_array([_image_struct(c, new.type) for c in column.chunks], new.type)
        elif name == "frames" and field.name == "instances" and version == 1:
            column = pa.chunked_array([_renamed_instances(c) for c in column.chunks])
        fields.append(new)
        columns.append(column.cast(new.type))
    return pa.Table.from_arrays(columns, schema=pa.schema(fields))


def upgrade_table(table: pa.Table, name: str, version: int) -> pa.Table:
    """Columns of a ``name`` ("frames"/"objects") table of schema ``version`` in the current schema.

    Works on any subset of columns; a table already in the current schema is returned as is.
    """
    if version not in KNOWN_VERSIONS:
        raise ValueError(f"no upgrade from record schema version {version}")
    for step in range(version, SCHEMA_VERSION):
        table = _step(table, name, step)
    return table
