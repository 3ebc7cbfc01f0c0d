"""Schema v1 tables as v2, converted column by column in Arrow.

The reader, the validator and ``usl-records migrate`` all go through ``upgrade_table``, so a v1
dataset reads exactly like its migrated copy. v1 -> v2: ``image`` bytes become the Image struct
``{bytes, path: null}``; instance ``bbox`` is renamed ``box_xyxy``; ``category_id`` widens to
int64; every field becomes nullable (see ``schema.table_schema``).
"""

from __future__ import annotations

import pyarrow as pa

from .schema import SCHEMA_VERSION, table_schema

RENAMED_INSTANCE_FIELDS = {"bbox": "box_xyxy"}


def _image_struct(chunk: pa.Array, type_: pa.StructType) -> pa.Array:
    return pa.StructArray.from_arrays([chunk, pa.nulls(len(chunk), pa.string())], fields=list(type_))


def _renamed_instances(chunk: pa.ListArray) -> pa.Array:
    """Rename struct fields by position; a cast alone would match by name and null them."""
    values = chunk.values
    names = [RENAMED_INSTANCE_FIELDS.get(f.name, f.name) for f in values.type]
    struct = pa.StructArray.from_arrays(values.flatten(), names=names)
    mask = chunk.is_null() if chunk.null_count else None
    return pa.ListArray.from_arrays(chunk.offsets, struct, mask=mask)


def upgrade_table(table: pa.Table, name: str, version: int) -> pa.Table:
    """Columns of a ``name`` ("frames"/"objects") table of schema ``version`` in the current schema.

    Works on any subset of columns; a table already in the current schema is returned as is.
    """
    if version == SCHEMA_VERSION:
        return table
    if version != 1:
        raise ValueError(f"no upgrade from record schema version {version}")
    target = table_schema(name)
    fields, columns = [], []
    for field, column in zip(table.schema, table.columns):
        new = target.field(field.name)
        if column.num_chunks == 0:  # an empty read has no chunks to convert
            column = pa.chunked_array([pa.array([], field.type)])
        if name == "frames" and field.name == "image":
            column = pa.chunked_array([_image_struct(c, new.type) for c in column.chunks], new.type)
        elif name == "frames" and field.name == "instances":
            column = pa.chunked_array([_renamed_instances(c) for c in column.chunks])
        fields.append(new)
        columns.append(column.cast(new.type))
    return pa.Table.from_arrays(columns, schema=pa.schema(fields))
