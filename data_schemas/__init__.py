"""JSON Schemas for every HDF5 layout (``stages/*.json``) and every config file (``configs/*.json``).

Stage schemas validate a *description* of an HDF5 file rather than the file itself::

    {"datasets": {"frames": {"dtype": "uint8", "shape": [2, 1, 60, 80, 3]}, ...},
     "attrs": {"mm_per_px": 0.1, ...}}

Three extension keywords sit beside the JSON Schema keywords of a stage schema:

``x-version``
    The layout's version, written into every file; bump it when the layout changes.
``x-reads``
    Optional: the versions this package still reads (default: only ``x-version``), for a
    change that only relaxed the layout (e.g. capture version 2 made ``reference`` optional,
    so a version-1 file is a valid version-2 file).
``x-dims``
    Symbolic shapes such as ``{"frames": ["K", "P", "H", "W", "C"]}``: a symbol must take
    the same value in every dataset it appears in, an integer must match exactly, ``"*"``
    matches anything. JSON Schema cannot relate one array's shape to another's, so
    :func:`check_dims` does.
``x-params``
    A JSON Schema of the stage's parameters, used to coerce them before hashing (an ``int``
    where the schema says ``number`` becomes a ``float``, so ``1`` and ``1.0`` give one key).

Config schemas are plain JSON Schemas with ``additionalProperties: false`` everywhere, so an
unknown or mistyped key is reported with its name and the allowed keys.
"""

from __future__ import annotations

import json
from functools import lru_cache
from importlib import resources
from pathlib import Path
from typing import Any, Mapping

import jsonschema

__all__ = [
    "SchemaError",
    "stage_schema",
    "config_schema",
    "provenance_schema",
    "stage_schema_names",
    "config_schema_names",
    "schema_version",
    "readable_versions",
    "validate_description",
    "check_dims",
    "validate_config",
    "load_config_file",
    "read_yaml_file",
    "coerce_params",
    "safe_load_yaml",
]


class SchemaError(ValueError):
    """A document or file does not satisfy its schema. The message names the source and field."""


def _schema_dir(kind: str) -> Path:
    return Path(str(resources.files("data_schemas") / kind))


@lru_cache(maxsize=None)
def _load(kind: str, name: str) -> dict:
    path = _schema_dir(kind) / f"{name}.json"
    if not path.is_file():
        known = ", ".join(_names(kind)) or "none"
        raise SchemaError(f"no {kind[:-1]} schema named {name!r} (known: {known})")
    with open(path, encoding="utf-8") as f:
        schema = json.load(f)
    jsonschema.Draft202012Validator.check_schema(schema)
    return schema


def _names(kind: str) -> list[str]:
    d = _schema_dir(kind)
    return sorted(p.stem for p in d.glob("*.json")) if d.is_dir() else []


def stage_schema(name: str) -> dict:
    """The JSON Schema of the HDF5 layout ``name`` (``capture``, ``normals``, ...)."""
    return _load("stages", name)


def config_schema(name: str) -> dict:
    """The JSON Schema of config files of kind ``name`` (``scene``, ``pipeline``, ``mode``, ...)."""
    return _load("configs", name)


def provenance_schema() -> dict:
    """The JSON Schema of the provenance attributes the store writes into every file."""
    return _load("common", "provenance")


def stage_schema_names() -> list[str]:
    """Names of all stage (HDF5 layout) schemas.

    Examples
    --------
    >>> {"capture", "calibration", "illumination", "normals", "depth"} <= set(stage_schema_names())
    True
    """
    return _names("stages")


def config_schema_names() -> list[str]:
    """Names of all config-file schemas."""
    return _names("configs")


def schema_version(name: str) -> int:
    """``x-version`` of a stage schema."""
    return int(stage_schema(name).get("x-version", 1))


def readable_versions(name: str) -> tuple[int, ...]:
    """The file versions of stage schema ``name`` that this package reads (``x-reads``, else
    just ``x-version``).

    Examples
    --------
    >>> readable_versions("capture")
    (1, 2)
    """
    s = stage_schema(name)
    return tuple(int(v) for v in s.get("x-reads", [s.get("x-version", 1)]))


def _path_of(error: jsonschema.ValidationError) -> str:
    parts = [str(p) for p in error.absolute_path]
    return "/".join(parts) if parts else "(top level)"


def _explain(error: jsonschema.ValidationError, root_hint: str = "") -> str:
    """Turn a jsonschema error into one line a user can act on."""
    where = _path_of(error)
    if error.validator == "additionalProperties":
        allowed = sorted((error.schema.get("properties") or {}).keys())
        extra = sorted(set(error.instance) - set(allowed)) if isinstance(error.instance, dict) else []
        key = ", ".join(repr(k) for k in extra) or "?"
        loc = "top level" if where == "(top level)" else where
        return f"unknown key {key} at {loc}; allowed keys: {', '.join(allowed)}"
    if error.validator == "required":
        return f"{where}: {error.message}"
    return f"{where}: {error.message}"


def validate_description(name: str, description: Mapping[str, Any], source: str = "<memory>") -> None:
    """Validate a file description against stage schema ``name``; raise :class:`SchemaError`.

    Checks the JSON Schema (required datasets, dtypes, ranks, required attributes) and the
    symbolic shapes of ``x-dims``.
    """
    schema = stage_schema(name)
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(description), key=lambda e: list(e.absolute_path))
    if errors:
        lines = "; ".join(_explain(e) for e in errors[:5])
        more = f" (+{len(errors) - 5} more)" if len(errors) > 5 else ""
        raise SchemaError(f"{source}: does not match schema {name!r}: {lines}{more}")
    check_dims(name, description.get("datasets", {}), source)


def check_dims(name: str, datasets: Mapping[str, Mapping[str, Any]], source: str = "<memory>") -> dict[str, int]:
    """Check the ``x-dims`` shape rules of stage schema ``name``; return the bound symbols.

    Examples
    --------
    >>> ds = {"normals": {"shape": [1, 4, 5, 3]}, "mask": {"shape": [1, 4, 5]}}
    >>> sorted(check_dims("normals", ds).items())
    [('H', 4), ('K', 1), ('W', 5)]
    """
    dims = stage_schema(name).get("x-dims", {})
    bound: dict[str, int] = {}
    where: dict[str, str] = {}
    for ds_name, rule in dims.items():
        if ds_name not in datasets:
            continue  # presence is the JSON Schema's business
        shape = list(datasets[ds_name].get("shape", []))
        if len(shape) != len(rule):
            raise SchemaError(
                f"{source}: dataset {ds_name!r} must have shape {_fmt_rule(rule)} "
                f"({len(rule)} dimensions), got {tuple(shape)}")
        for axis, (sym, size) in enumerate(zip(rule, shape)):
            if sym == "*":
                continue
            if isinstance(sym, int):
                if size != sym:
                    raise SchemaError(
                        f"{source}: dataset {ds_name!r} must have shape {_fmt_rule(rule)}, "
                        f"got {tuple(shape)} (axis {axis} must be {sym})")
                continue
            if sym in bound and bound[sym] != size:
                raise SchemaError(
                    f"{source}: dataset {ds_name!r} has {sym}={size} (shape {tuple(shape)}) but "
                    f"{where[sym]} has {sym}={bound[sym]}")
            bound.setdefault(sym, size)
            where.setdefault(sym, repr(ds_name))
    return bound


def _fmt_rule(rule) -> str:
    return "(" + ", ".join(str(s) for s in rule) + ")"


def validate_config(kind: str, obj: Any, source: str = "<memory>",
                    choices: Mapping[str, Any] | None = None) -> Any:
    """Validate a parsed config (YAML/JSON) against ``configs/<kind>.json``; return it.

    A schema node with ``"x-choices": NAME`` takes its allowed values (``enum``) from
    ``choices[NAME]``: the registries that own those names (solvers, integrators, contact
    objects) live above this package, so the caller passes them in. Without them the node
    only checks its type.

    Raises
    ------
    SchemaError
        Naming ``source``, the offending key path and, for unknown keys, the allowed keys.

    Examples
    --------
    >>> validate_config("pipeline", {"cache": "c", "colour": 1}, "run.yaml")
    Traceback (most recent call last):
    ...
    data_schemas.SchemaError: run.yaml: unknown key 'colour' at top level; allowed keys: ...
    """
    schema = _with_choices(config_schema(kind), choices or {})
    validator = jsonschema.Draft202012Validator(schema)
    errors = sorted(validator.iter_errors(obj), key=lambda e: (len(list(e.absolute_path)), list(map(str, e.absolute_path))))
    if errors:
        # The most specific error first: unknown keys are the commonest mistake.
        errors.sort(key=lambda e: e.validator != "additionalProperties")
        raise SchemaError(f"{source}: {_explain(errors[0])}")
    return obj


def _with_choices(schema: Any, choices: Mapping[str, Any]) -> Any:
    """A copy of ``schema`` whose ``x-choices`` nodes carry the ``enum`` of their registry."""
    if isinstance(schema, Mapping):
        out = {k: _with_choices(v, choices) for k, v in schema.items()}
        name = schema.get("x-choices")
        if isinstance(name, str) and name in choices:
            out["enum"] = list(choices[name])
        return out
    if isinstance(schema, list):
        return [_with_choices(v, choices) for v in schema]
    return schema


def safe_load_yaml(stream) -> Any:
    """``yaml.safe_load`` through libyaml's C parser where PyYAML has it (the pure-Python one otherwise).

    The same safe constructor either way, so the same objects and the same ``yaml.YAMLError``
    family on bad input; only the parsing is faster (the 20 KB ``point`` mode: 58 ms -> 10 ms,
    and every capture, calibration and comparison loads its modes). The project's one YAML
    reader: every config, mode, profile and scene file goes through it.

    Examples
    --------
    >>> safe_load_yaml("a: [1, 2.5, x]")
    {'a': [1, 2.5, 'x']}
    """
    import yaml

    return yaml.load(stream, Loader=getattr(yaml, "CSafeLoader", yaml.SafeLoader))


def read_yaml_file(path: str | Path) -> Any:
    """The parsed YAML (or JSON) of a file read as UTF-8 (:func:`safe_load_yaml`): every config, mode,
    profile and scene file is read here. A file that is not UTF-8 or not YAML is one SchemaError,
    ``"<path>: not valid YAML: <the parser's message on one line>"``.

    Examples
    --------
    >>> import tempfile
    >>> p = Path(tempfile.mkdtemp()) / "bad.yaml"
    >>> _ = p.write_bytes(b"a: [1,")
    >>> try:
    ...     read_yaml_file(p)
    ... except SchemaError as exc:
    ...     print(str(exc).startswith(f"{p}: not valid YAML: while parsing"), len(str(exc).splitlines()))
    True 1
    """
    import yaml

    try:
        with open(path, encoding="utf-8") as f:
            return safe_load_yaml(f)
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise SchemaError(f"{path}: not valid YAML: {' '.join(str(exc).split())}") from None


def load_config_file(kind: str, path: str | Path) -> Any:
    """Read a YAML or JSON config file and validate it as ``kind`` (SchemaError naming the file: missing,
    not YAML, not UTF-8, or the key that breaks the schema)."""
    path = Path(path)
    if not path.is_file():
        raise SchemaError(f"{path}: no such file")
    obj = read_yaml_file(path)
    if obj is None:
        obj = {}
    return validate_config(kind, obj, str(path))


def coerce_params(params: Any, schema: Mapping[str, Any] | None) -> Any:
    """Coerce parameters to the types their schema declares before hashing.

    Integers where the schema says ``number`` become floats; nested objects and arrays are
    walked. Values the schema does not describe are left as they are.

    Examples
    --------
    >>> coerce_params({"a": 1, "b": [2]}, {"properties": {"a": {"type": "number"},
    ...     "b": {"type": "array", "items": {"type": "number"}}}})
    {'a': 1.0, 'b': [2.0]}
    """
    if schema is None:
        return params
    types = schema.get("type")
    types = [types] if isinstance(types, str) else (types or [])
    if isinstance(params, bool):
        return params
    if isinstance(params, int) and "number" in types and "integer" not in types:
        return float(params)
    if isinstance(params, Mapping):
        props = schema.get("properties", {})
        extra = schema.get("additionalProperties")
        extra = extra if isinstance(extra, Mapping) else None
        return {k: coerce_params(v, props.get(k, extra)) for k, v in params.items()}
    if isinstance(params, (list, tuple)):
        items = schema.get("items")
        if isinstance(items, Mapping):
            return [coerce_params(v, items) for v in params]
        return list(params)
    return params
