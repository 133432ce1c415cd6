"""Build a minimal valid record for any stage schema, straight from the schema itself.

Round-trip tests use this so that a stage owner who extends a layout gets the new fields
exercised without editing the tests.
"""

from __future__ import annotations

import numpy as np

import data_schemas
from pipeline.base.store import Record

SYMBOL_SIZES = {"K": 2, "P": 3, "H": 4, "W": 5, "C": 3, "L": 6, "D": 2}


def example_value(schema: dict):
    if "const" in schema:
        return schema["const"]
    if "enum" in schema:
        return schema["enum"][0]
    t = schema.get("type")
    t = t[0] if isinstance(t, list) else t
    if t == "number":
        lo = schema.get("minimum", schema.get("exclusiveMinimum", 0.0))
        return float(lo) + 0.5
    if t == "integer":
        return int(schema.get("minimum", 1)) + 1 if "maximum" not in schema else int(schema.get("minimum", 1))
    if t == "string":
        return "example"
    if t == "boolean":
        return True
    if t == "array":
        return [example_value(schema.get("items", {"type": "string"}))] * max(1, schema.get("minItems", 1))
    if t == "object":
        return {k: example_value(v) for k, v in schema.get("properties", {}).items() if k in schema.get("required", [])}
    return "example"


def example_record(name: str, rng=None, all_datasets: bool = True) -> Record:
    rng = rng or np.random.default_rng(0)
    schema = data_schemas.stage_schema(name)
    dims = schema.get("x-dims", {})
    ds_props = schema["properties"]["datasets"]
    wanted = list(ds_props.get("properties", {})) if all_datasets else list(ds_props.get("required", []))
    data = {}
    for ds in wanted:
        spec = ds_props["properties"][ds]["properties"]
        dtype = spec["dtype"]["enum"][0]
        ndim = spec["shape"]["minItems"]
        rule = dims.get(ds, ["*"] * ndim)
        shape = tuple(s if isinstance(s, int) else SYMBOL_SIZES.get(s, 2) for s in rule)
        if dtype == "bool":
            arr = rng.random(shape) > 0.5
        elif dtype == "str":
            arr = np.array(["a"] * int(np.prod(shape))).reshape(shape)
        elif np.dtype(dtype).kind in "ui":
            arr = rng.integers(0, 200, size=shape).astype(dtype)
        else:
            arr = rng.standard_normal(shape).astype(dtype)
        data[ds] = arr
    attrs_schema = schema["properties"]["attrs"]
    meta = {k: example_value(attrs_schema["properties"][k]) for k in attrs_schema.get("required", [])}
    return Record(schema=name, data=data, meta=meta)
