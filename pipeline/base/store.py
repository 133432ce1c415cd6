"""The stage store: the one way every stage reads and writes HDF5.

An entry is ``<root>/<stage>/<digest>.h5`` where ``digest`` hashes (stage, stage version,
canonical parameters, input keys). Files are written to a temporary file in the same folder,
flushed, fsynced and renamed into place, so a crash at any point leaves either the old state
or a complete new entry, never a half-written file under an entry's name. Every file carries
provenance attributes and is validated against its schema in ``data_schemas/`` on write and
on read; a bad file raises :class:`StoreError` naming the file and the problem.

Examples
--------
>>> import tempfile, numpy as np
>>> store = StageStore(tempfile.mkdtemp())
>>> key = store.key("depth", 1, {"integrator": "dst"}, inputs=["abc"])
>>> store.get(key) is None
True
>>> rec = Record("depth", {"height": np.zeros((1, 4, 5), np.float32),
...                        "mask": np.ones((1, 4, 5), bool)},
...              {"integrator": "dst", "mm_per_px": 0.1})
>>> _ = store.put(key, rec)
>>> store.get(key).data["height"].shape
(1, 4, 5)
"""

from __future__ import annotations

import datetime as _dt
import hashlib
import json
import logging
import os
import re
import secrets
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterator, Mapping, Sequence

import numpy as np

import data_schemas
from pipeline import __version__
from pipeline.base.errors import UserError
from pipeline.base.frame_codec import h5py_with_filters, read_frames, write_frames
from pipeline.base.hashing import canonical, canonical_json, digest

__all__ = [
    "StoreError",
    "StageKey",
    "Record",
    "StageStore",
    "EntryInfo",
    "default_store_root",
    "write_record",
    "read_record",
    "describe_file",
    "provenance_attrs",
    "replace_datasets",
    "create_dataset",
    "write_attrs",
    "LazyDataset",
    "DIGEST_ATTR",
    "crc_digest",
    "check_digest",
    "frame_checksum",
]

_log = logging.getLogger("iristac")

_PROV = "iristac_"
_JSON_ATTRS = "iristac_json_attrs"
_ENTRY_RE = re.compile(r"^[0-9a-f]{32}\.h5$")
_TEMP_RE = re.compile(r"^\.(?P<name>[^.]+)\.(?P<pid>\d+)\.(?P<rand>[0-9a-f]+)\.tmp\.h5$")
_QUARANTINE_RE = re.compile(r"^[0-9a-f]{32}\.bad-\d+\.h5$")
# A streamed entry being written (pipeline.base.streamed): its partial file and progress files.
_PARTIAL_RE = re.compile(r"^\.[0-9a-f]{32}\.(partial\.h5|progress-\d+\.json)$")
# Datasets at least this large get compressed (and chunked); small ones stay contiguous.
_COMPRESS_MIN_ELEMENTS = 4096
#: Schemas whose ``frames`` stack is written in the frames layout (:mod:`pipeline.base.frame_codec`:
#: Zstandard chunks of one frame set, checksummed, decoded on many threads by ``H5Frames``);
#: every other large dataset is LZF, shuffle and Fletcher-32 (docs/storage.md says why).
FRAME_SCHEMAS = ("capture", "recording")


class StoreError(UserError):
    """A store file is missing, unreadable, corrupt, or does not match its schema.

    ``path`` is the file, ``problem`` says what is wrong with it.
    """

    def __init__(self, path: str | os.PathLike, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")


def default_store_root() -> Path:
    """``$IRISTAC_CACHE`` if set, else ``./iristac-cache``."""
    return Path(os.environ.get("IRISTAC_CACHE", "iristac-cache"))


@dataclass(frozen=True)
class StageKey:
    """Identity of one stage result: what was computed, how, and from what."""

    stage: str
    version: int
    params: Any
    inputs: tuple[str, ...]
    digest: str
    schema: str

    @property
    def params_json(self) -> str:
        return canonical_json(self.params)


@dataclass
class Record:
    """The content of one HDF5 file: named arrays plus JSON-serialisable attributes.

    Attributes
    ----------
    schema : str
        Stage schema name (``capture``, ``calibration``, ``illumination``, ``normals``, ``depth``).
    data : dict[str, ndarray]
        Dataset path (``"frames"``, ``"truth/height"``) to array.
    meta : dict
        Attributes. Scalars are stored natively, containers as JSON.
    provenance : dict
        Filled on read: the ``iristac_*`` attributes (key, stage, params, ...).
    path : Path or None
        Filled on read and write.
    """

    schema: str
    data: dict[str, np.ndarray]
    meta: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    path: Path | None = None

    def describe(self) -> dict:
        """The description validated against the schema (see :mod:`data_schemas`)."""
        return {
            "datasets": {k: {"dtype": _dtype_name(np.asarray(v)), "shape": list(np.shape(v))}
                         for k, v in self.data.items()},
            "attrs": _jsonable(self.meta),
        }

    def validate(self, source: str = "<memory>") -> None:
        """Raise :class:`StoreError` unless the record matches its schema."""
        try:
            data_schemas.validate_description(self.schema, self.describe(), source)
        except data_schemas.SchemaError as exc:
            raise StoreError(source, f"invalid {self.schema!r} record: {_strip_source(str(exc), source)}") from None


def _strip_source(msg: str, source: str) -> str:
    prefix = f"{source}: "
    return msg[len(prefix):] if msg.startswith(prefix) else msg


def _dtype_name(a: np.ndarray) -> str:
    if a.dtype.kind in "US" or a.dtype == object:
        return "str"
    return str(a.dtype)


def _jsonable(obj: Any) -> Any:
    """Meta values as plain JSON types (numpy scalars and arrays converted)."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


# ----------------------------------------------------------------------------------------
# Writing and reading single files
# ----------------------------------------------------------------------------------------

def _chunks_for(shape: tuple[int, ...]) -> tuple[int, ...] | bool:
    """One image (the last three axes) per chunk for stacks; h5py's guess otherwise."""
    if len(shape) >= 3 and all(s > 0 for s in shape):
        chunk = (1,) * (len(shape) - 3) + tuple(shape[-3:])
        if int(np.prod(chunk)) * 8 <= 8 * 2**20:
            return chunk
    return True


def _create_dataset(f, name: str, value) -> None:
    """One dataset as every store file holds it: strings as UTF-8, checksummed, large ones compressed."""
    h5py = h5py_with_filters()

    arr = np.asarray(value)
    if arr.dtype.kind == "U" or arr.dtype == object:
        f.create_dataset(name, data=np.asarray(arr, dtype=object).astype(str).tolist(), dtype=h5py.string_dtype())
        return
    kwargs: dict[str, Any] = {}
    if arr.ndim >= 1 and arr.size >= _COMPRESS_MIN_ELEMENTS:
        kwargs.update(chunks=_chunks_for(arr.shape), compression="lzf", shuffle=True, fletcher32=True)
    elif arr.ndim >= 1 and arr.size > 0:
        kwargs.update(chunks=True, fletcher32=True)
    f.create_dataset(name, data=arr, **kwargs)


def create_dataset(f, name: str, value) -> None:
    """Write ``value`` as dataset ``name`` of the open h5py file ``f`` as every store file holds
    it (strings as UTF-8, checksummed, large ones compressed)."""
    _create_dataset(f, name, value)


def write_attrs(f, meta: Mapping[str, Any], provenance: Mapping[str, str | int] | None, *,
                merge: bool = False) -> None:
    """``meta`` (scalars natively, containers as JSON) and ``provenance`` as the attributes of the
    open h5py file ``f``, as :func:`read_record` reads them back; ``merge``: added to the
    attributes already there (their JSON list kept)."""
    json_keys = set(json.loads(f.attrs[_JSON_ATTRS])) if merge and _JSON_ATTRS in f.attrs else set()
    for k, v in _jsonable(meta).items():
        if k.startswith(_PROV):
            raise StoreError(f.filename, f"meta key {k!r} is reserved for the store's provenance attributes")
        if isinstance(v, (bool, int, float, str)):
            f.attrs[k] = v
            json_keys.discard(k)
        else:
            f.attrs[k] = json.dumps(v)
            json_keys.add(k)
    for k, v in (provenance or {}).items():
        f.attrs[k] = v
    f.attrs[_JSON_ATTRS] = json.dumps(sorted(json_keys))


def _write_dataset(f, schema: str, name: str, value) -> None:
    """One dataset of a file of ``schema``: ``frames`` of :data:`FRAME_SCHEMAS` in the frames
    layout, everything else as :func:`_create_dataset` writes it."""
    arr = np.asarray(value)
    if name == "frames" and schema in FRAME_SCHEMAS and arr.dtype.kind in "biuf" and arr.ndim >= 2:
        write_frames(f, name, arr)
    else:
        _create_dataset(f, name, value)


def _write_h5(path: Path, record: Record, provenance: Mapping[str, str | int]) -> None:
    h5py = h5py_with_filters()

    with h5py.File(path, "w", libver="latest") as f:
        for name, value in record.data.items():
            _write_dataset(f, record.schema, name, value)
        write_attrs(f, record.meta, provenance)
        f.flush()


def fsync_file(path: Path) -> None:
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def fsync_dir(path: Path) -> None:
    try:
        fd = os.open(path, os.O_RDONLY)
    except OSError:
        return
    try:
        os.fsync(fd)
    except OSError:
        pass
    finally:
        os.close(fd)


def _temp_name(final: Path) -> Path:
    return final.with_name(f".{final.stem}.{os.getpid()}.{secrets.token_hex(6)}.tmp.h5")


def provenance_attrs(schema: str, key: StageKey | None = None) -> dict[str, str | int]:
    """The provenance attributes a file of ``schema`` carries (what :func:`write_record`
    writes; a writer that builds its file itself, like the live recorder's master file of
    virtual datasets, writes these so :func:`read_record` accepts it)."""
    return {
        "iristac_schema": schema,
        "iristac_schema_version": data_schemas.schema_version(schema),
        "iristac_key": key.digest if key else "",
        "iristac_stage": key.stage if key else "file",
        "iristac_params": key.params_json if key else "{}",
        "iristac_inputs": json.dumps(list(key.inputs)) if key else "[]",
        "iristac_version": __version__,
        "iristac_created": _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds"),
    }


def write_record(path: str | os.PathLike, record: Record, key: StageKey | None = None) -> Path:
    """Validate ``record`` and write it atomically to ``path``.

    The file appears under its final name only once it is complete and fsynced; a crash
    leaves at most a ``.*.tmp.h5`` file beside it (removed by ``iristac cache gc``).

    Parameters
    ----------
    path : path-like
        Destination (``.h5``). Its folder is created if needed.
    record : Record
        What to write.
    key : StageKey, optional
        The stage key, recorded in the provenance attributes (a standalone file written
        outside a store gets the stage ``"file"`` and an empty key).

    Returns
    -------
    Path
        The final path.
    """
    final = Path(path)
    record.validate(str(final))
    final.parent.mkdir(parents=True, exist_ok=True)
    provenance = provenance_attrs(record.schema, key)
    _write_atomically(final, lambda tmp: _write_h5(tmp, record, provenance))
    record.path = final
    record.provenance = dict(provenance)
    return final


def _write_atomically(final: Path, build: Callable[[Path], None]) -> None:
    """``build(tmp)`` makes the file at a temporary name beside ``final``; then fsync and rename
    it into place (atomic on POSIX; concurrent writers: last rename wins, both valid). On any
    error the temporary file is removed and ``final`` is untouched."""
    tmp = _temp_name(final)
    try:
        build(tmp)
        fsync_file(tmp)
        os.replace(tmp, final)
    except BaseException:
        try:
            tmp.unlink()
        except FileNotFoundError:
            pass
        raise
    fsync_dir(final.parent)


def replace_datasets(path: str | os.PathLike, updates: Mapping[str, Any]) -> Path:
    """Atomically replace, add or (value ``None``) remove some datasets of a store file.

    For small changes to a large file (a capture's hand labels): the file is copied to a
    temporary file beside it, changed there, validated against its schema, fsynced and renamed
    into place, so the file under ``path`` is at every moment either the old one or the new
    one, and a bad change (one its schema refuses) leaves it untouched.

    Examples
    --------
    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "d.h5")
    >>> rec = Record("depth", {"height": np.zeros((1, 4, 5), np.float32), "mask": np.ones((1, 4, 5), bool)},
    ...              {"integrator": "dst", "mm_per_px": 0.1})
    >>> _ = write_record(p, rec)
    >>> _ = replace_datasets(p, {"height": np.ones((1, 4, 5), np.float32)})
    >>> float(read_record(p).data["height"].sum())
    20.0
    """
    import shutil

    h5py = h5py_with_filters()

    final = Path(path)
    _, provenance = describe_file(final)
    _check_provenance(final, provenance)
    schema = provenance["iristac_schema"]

    def build(tmp: Path) -> None:
        shutil.copyfile(final, tmp)
        with h5py.File(tmp, "r+") as f:
            for name, value in updates.items():
                if name in f:
                    del f[name]
                if value is not None:
                    _write_dataset(f, schema, name, value)
            f.flush()
        description, _ = describe_file(tmp)
        try:
            data_schemas.validate_description(schema, description, str(final))
        except data_schemas.SchemaError as exc:
            raise StoreError(final, f"change refused, file left as it was: {_strip_source(str(exc), str(final))}") \
                from None

    _write_atomically(final, build)
    return final


def describe_file(path: str | os.PathLike) -> tuple[dict, dict]:
    """Read the structure of an HDF5 file without its data: (description, provenance).

    Raises :class:`StoreError` if the file cannot be opened or parsed.
    """
    h5py = h5py_with_filters()

    path = Path(path)
    if not path.is_file():
        raise StoreError(path, "no such file")
    try:
        with h5py.File(path, "r") as f:
            datasets: dict[str, dict] = {}

            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    dtype = "str" if h5py.check_string_dtype(obj.dtype) else str(obj.dtype)
                    datasets[name] = {"dtype": dtype, "shape": list(obj.shape)}

            f.visititems(visit)
            attrs = {k: _attr_value(v) for k, v in f.attrs.items()}
    except StoreError:
        raise
    except Exception as exc:  # h5py raises OSError/KeyError/RuntimeError on damaged files
        raise StoreError(path, f"not a readable HDF5 file (truncated or corrupt?): {exc}") from None
    json_keys = set()
    if _JSON_ATTRS in attrs:
        try:
            json_keys = set(json.loads(attrs[_JSON_ATTRS]))
        except (TypeError, ValueError):
            raise StoreError(path, f"attribute {_JSON_ATTRS!r} is not a JSON list") from None
    provenance = {k: v for k, v in attrs.items() if k.startswith(_PROV)}
    meta = {}
    for k, v in attrs.items():
        if k.startswith(_PROV):
            continue
        if k in json_keys:
            try:
                v = json.loads(v)
            except (TypeError, ValueError):
                raise StoreError(path, f"attribute {k!r} should hold JSON, got {v!r:.80}") from None
        meta[k] = v
    return {"datasets": datasets, "attrs": meta}, provenance


def _attr_value(v: Any) -> Any:
    if isinstance(v, bytes):
        return v.decode("utf-8", "replace")
    if isinstance(v, np.generic):
        return v.item()
    if isinstance(v, np.ndarray):
        return v.tolist()
    return v


def _check_provenance(path: Path, provenance: Mapping[str, Any]) -> None:
    import jsonschema

    errors = list(jsonschema.Draft202012Validator(data_schemas.provenance_schema()).iter_errors(dict(provenance)))
    if errors:
        raise StoreError(path, "not an IrisTac store file: " + "; ".join(e.message for e in errors[:3]))


#: The attribute holding a streamed file's content digest (:mod:`pipeline.base.streamed`: a checksum
#: of each frame's datasets, :func:`frame_checksum`): its data are unfiltered, so this, not a
#: Fletcher-32 filter, finds a flipped bit.
DIGEST_ATTR = "stream_digest"


def frame_checksum(arrays, k: int) -> int:
    """A 64-bit checksum of frame ``k`` of ``arrays`` (datasets in order): per dataset, the sum and
    the XOR of its bytes as little-endian 64-bit words (the last one zero-padded), mixed with the
    running value. Any flipped bit changes it; it reads memory at numpy's pace (a 320 x 240 frame's
    results, 1.4 MB: 0.02 ms against zlib CRC-32's 0.33 ms, which cost a frame pipeline's threads
    time on two cores).

    >>> a = np.zeros((2, 3, 5), np.float32)
    >>> b = a.copy(); b.view(np.uint8)[1, 0, 2] ^= 4
    >>> frame_checksum([a], 1) != frame_checksum([b], 1), frame_checksum([a], 0) == frame_checksum([b], 0)
    (True, True)
    """
    mask = (1 << 64) - 1
    value = 0
    for a in arrays:
        raw = np.ascontiguousarray(a[k]).reshape(-1).view(np.uint8)
        n = len(raw) // 8 * 8
        words = raw[:n].view("<u8")
        s = int(np.add.reduce(words, dtype=np.uint64)) if n else 0
        x = int(np.bitwise_xor.reduce(words)) if n else 0
        if n < len(raw):
            tail = int.from_bytes(raw[n:].tobytes(), "little")
            s, x = (s + tail) & mask, x ^ tail
        value = (value * 1099511628211 + s * 31 + x + len(raw)) & mask
    return value


def crc_digest(crcs: list[int]) -> str:
    """The content digest of the per-frame checksums, in frame order (:data:`DIGEST_ATTR`)."""
    return hashlib.sha256(np.asarray(crcs, np.uint64).tobytes()).hexdigest()[:32]


def check_digest(path, data: Mapping[str, Any], meta: Mapping[str, Any]) -> None:
    """A finished streamed file's datasets against its :data:`DIGEST_ATTR` (the per-frame
    checksums of its per-frame datasets, in name order); a mismatch is a :class:`StoreError`
    naming the file. Files without the attribute (not streamed) pass: their datasets carry
    Fletcher-32 checksums that HDF5 checks on reading."""
    want = meta.get(DIGEST_ATTR)
    layout = meta.get("stream_datasets")
    if not want or not layout:
        return
    names = sorted(layout)
    frames = len(np.asarray(data[names[0]])) if names else 0
    arrays = [np.asarray(data[name]) for name in names]
    if crc_digest([frame_checksum(arrays, k) for k in range(frames)]) != want:
        raise StoreError(path, f"its data do not match its {DIGEST_ATTR} (a bit flipped on disk?)")


class LazyDataset:
    """A dataset of a store file read only where it is indexed: ``shape``, ``dtype``, ``ndim``,
    ``len()``, ``ds[a:b]`` (reads those rows; the file is opened for each read) and
    ``np.asarray(ds)`` (reads it all). What :func:`read_record` gives for datasets above
    ``lazy_bytes``, so a long recording's frames stay on disk until a chunk of them is needed.

    Examples
    --------
    >>> import tempfile, os
    >>> p = os.path.join(tempfile.mkdtemp(), "d.h5")
    >>> rec = Record("depth", {"height": np.arange(40, dtype=np.float32).reshape(2, 4, 5),
    ...                        "mask": np.ones((2, 4, 5), bool)}, {"integrator": "dst", "mm_per_px": 0.1})
    >>> _ = write_record(p, rec)
    >>> lazy = read_record(p, lazy_bytes=100).data["height"]
    >>> lazy.shape, float(lazy[1:2].sum()), np.asarray(lazy).dtype
    ((2, 4, 5), 590.0, dtype('float32'))
    """

    def __init__(self, path: str | os.PathLike, name: str, shape: tuple, dtype):
        self.path, self.name = Path(path), name
        self.shape, self.dtype = tuple(int(s) for s in shape), np.dtype(dtype)
        self.ndim = len(self.shape)
        self.size = int(np.prod(self.shape, dtype=np.int64))

    def __len__(self) -> int:
        return self.shape[0] if self.shape else 0

    def __getitem__(self, index):
        h5py = h5py_with_filters()
        try:
            with h5py.File(self.path, "r") as f:
                return f[self.name][index]
        except Exception as exc:
            raise StoreError(self.path, f"cannot read dataset {self.name!r} {index!r} (truncated or corrupt?): "
                                        f"{exc}") from None

    def __array__(self, dtype=None, copy=None):
        a = self[()]
        return a if dtype is None else a.astype(dtype)


def read_record(path: str | os.PathLike, schema: str | None = None, *, load: bool = True,
                lazy_bytes: int | None = None) -> Record:
    """Read and validate one file written by :func:`write_record` or the store.

    Parameters
    ----------
    path : path-like
        The ``.h5`` file.
    schema : str, optional
        Expected schema name; a file of another schema is an error.
    load : bool
        Read the datasets (checksums verified). With ``False`` only the structure is checked
        and ``data`` is empty.
    lazy_bytes : int, optional
        Datasets larger than this are not read but given as :class:`LazyDataset` (read where
        indexed): a recording's frames and per-frame truth, read a chunk at a time.

    Raises
    ------
    StoreError
        Naming the file and the problem: missing, not HDF5, truncated, checksum mismatch,
        wrong schema, schema violation, newer layout version than this package knows.
    """
    h5py = h5py_with_filters()

    path = Path(path)
    description, provenance = describe_file(path)
    _check_provenance(path, provenance)
    found = provenance["iristac_schema"]
    if schema is not None and found != schema:
        raise StoreError(path, f"expected a {schema!r} file, found schema {found!r}")
    try:
        known = data_schemas.schema_version(found)
    except data_schemas.SchemaError as exc:
        raise StoreError(path, str(exc)) from None
    readable = data_schemas.readable_versions(found)
    if int(provenance["iristac_schema_version"]) not in readable:
        raise StoreError(path, f"schema {found!r} version {provenance['iristac_schema_version']} "
                               f"but this package reads version {' or '.join(map(str, readable))} "
                               f"(writes {known}); recompute it")
    try:
        data_schemas.validate_description(found, description, str(path))
    except data_schemas.SchemaError as exc:
        raise StoreError(path, _strip_source(str(exc), str(path))) from None
    data: dict[str, np.ndarray] = {}
    if load:
        try:
            with h5py.File(path, "r") as f:
                for name, info in description["datasets"].items():
                    ds = f[name]
                    if lazy_bytes is not None and info["dtype"] != "str" and \
                            ds.size * ds.dtype.itemsize > lazy_bytes:
                        data[name] = LazyDataset(path, name, ds.shape, ds.dtype)  # type: ignore[assignment]
                        continue
                    if info["dtype"] == "str":
                        data[name] = np.asarray(ds.asstr()[()], dtype=str)
                    else:
                        data[name] = read_frames(ds)  # zstd chunks: checksums verified; else ds[()]
        except Exception as exc:
            raise StoreError(path, f"cannot read dataset data (truncated or corrupt?): {exc}") from None
    return Record(schema=found, data=data, meta=description["attrs"], provenance=provenance, path=path)


# ----------------------------------------------------------------------------------------
# The store
# ----------------------------------------------------------------------------------------

@dataclass
class EntryInfo:
    """One file in the store, as ``ls``/``verify``/``gc`` see it."""

    path: Path
    stage: str
    kind: str  # "entry", "temp", "quarantined", "partial" (a streamed entry being written), "foreign"
    size: int
    schema: str | None = None
    key: str | None = None
    created: str | None = None
    problem: str | None = None


class StageStore:
    """A folder of validated, content-addressed HDF5 files, one per stage result.

    Parameters
    ----------
    root : path-like, optional
        The store folder (created on first write). Default :func:`default_store_root`.
    """

    def __init__(self, root: str | os.PathLike | None = None):
        self.root = Path(root) if root is not None else default_store_root()

    # -- keys ----------------------------------------------------------------------------
    def key(self, stage: str, version: int, params: Mapping[str, Any] | None = None,
            inputs: Sequence[str | StageKey] = (), schema: str | None = None) -> StageKey:
        """The key of a stage result.

        Parameters are coerced by the schema's ``x-params`` (ints to floats where it says
        ``number``) and canonically encoded; inputs are the keys (or digests) of the results
        this one was computed from, in order. ``schema`` is the schema the stage writes
        (default: the stage's name; each stage module of :mod:`pipeline.stages` passes its own).

        Examples
        --------
        >>> s = StageStore("unused")
        >>> a = s.key("normals", 1, {"solver": "lstsq", "max_condition": 100})
        >>> b = s.key("normals", 1, {"max_condition": 100.0, "solver": "lstsq"})
        >>> a.digest == b.digest, a.digest == s.key("normals", 2, {"solver": "lstsq"}).digest
        (True, False)
        """
        if not re.fullmatch(r"[A-Za-z0-9_-]+", stage):
            raise ValueError(f"stage name must be letters, digits, '_' or '-', got {stage!r}")
        schema = schema or stage  # a stage writes the schema of its name unless told (pipeline.stages)
        try:
            param_schema = data_schemas.stage_schema(schema).get("x-params")
        except data_schemas.SchemaError:
            raise ValueError(f"stage {stage!r}: no schema named {schema!r} "
                             f"(known: {', '.join(data_schemas.stage_schema_names())})") from None
        params = canonical(data_schemas.coerce_params(dict(params or {}), param_schema))
        input_keys = tuple(k.digest if isinstance(k, StageKey) else str(k) for k in inputs)
        d = digest({"stage": stage, "version": int(version), "params": params, "inputs": list(input_keys)})
        return StageKey(stage=stage, version=int(version), params=params, inputs=input_keys, digest=d, schema=schema)

    def path_for(self, key: StageKey) -> Path:
        """Where the entry of ``key`` lives."""
        return self.root / key.stage / f"{key.digest}.h5"

    # -- get / put -----------------------------------------------------------------------
    def contains(self, key: StageKey) -> bool:
        """Whether an entry file exists for ``key`` (not whether it is valid)."""
        return self.path_for(key).is_file()

    def get(self, key: StageKey, *, recompute_bad: bool = False, load: bool = True) -> Record | None:
        """The stored result of ``key``, or ``None`` if there is none.

        A bad file (truncated, corrupt, wrong schema) raises :class:`StoreError`, unless
        ``recompute_bad`` is set: then it is quarantined (moved aside to
        ``<digest>.bad-<time>.h5``, kept, never deleted), one warning line naming the file and
        the problem goes to the ``iristac`` logger, and it is treated as a miss, so the
        caller recomputes it: the cache heals itself.
        """
        path = self.path_for(key)
        if not path.exists():
            return None
        try:
            rec = read_record(path, key.schema, load=load)
            if load:
                check_digest(path, rec.data, rec.meta)
            if rec.provenance.get("iristac_key") != key.digest:
                raise StoreError(path, f"file records key {rec.provenance.get('iristac_key')!r}, "
                                       f"expected {key.digest!r} (file renamed or copied by hand?)")
        except StoreError as exc:
            if not recompute_bad:
                raise
            problem = exc.problem
            stamp = int(_dt.datetime.now().timestamp() * 1000)
            bad = path.with_name(f"{key.digest}.bad-{stamp}.h5")
            os.replace(path, bad)
            _log.warning("cache entry %s was bad (%s); quarantined as %s and recomputed", path, problem, bad.name)
            return None
        return rec

    def put(self, key: StageKey, record: Record) -> Path:
        """Validate and atomically write ``record`` as the entry of ``key``."""
        if record.schema != key.schema:
            raise StoreError(self.path_for(key), f"stage {key.stage!r} stores schema {key.schema!r}, "
                                                 f"got a {record.schema!r} record")
        return write_record(self.path_for(key), record, key)

    def get_or_compute(self, key: StageKey, compute: Callable[[], Record], *,
                       recompute_bad: bool = False, force: bool = False) -> tuple[Record, bool]:
        """``(record, cached)``: the stored result, or ``compute()`` stored and returned."""
        if not force:
            rec = self.get(key, recompute_bad=recompute_bad)
            if rec is not None:
                return rec, True
        rec = compute()
        self.put(key, rec)
        return rec, False

    # -- maintenance ---------------------------------------------------------------------
    def _files(self) -> Iterator[tuple[str, Path]]:
        if not self.root.is_dir():
            return
        for stage_dir in sorted(p for p in self.root.iterdir() if p.is_dir()):
            for p in sorted(stage_dir.iterdir()):
                if p.is_file():
                    yield stage_dir.name, p

    def entries(self, check: bool = False) -> list[EntryInfo]:
        """Every file in the store, classified; with ``check``, entries are fully verified."""
        out = []
        for stage, p in self._files():
            size = p.stat().st_size
            if _TEMP_RE.match(p.name):
                out.append(EntryInfo(p, stage, "temp", size))
            elif _PARTIAL_RE.match(p.name):
                out.append(EntryInfo(p, stage, "partial", size))
            elif _QUARANTINE_RE.match(p.name):
                out.append(EntryInfo(p, stage, "quarantined", size))
            elif _ENTRY_RE.match(p.name):
                info = EntryInfo(p, stage, "entry", size, key=p.stem)
                try:
                    rec = read_record(p, load=check)
                    info.schema = rec.schema
                    info.created = rec.provenance.get("iristac_created")
                    if rec.provenance.get("iristac_key") != p.stem:
                        info.problem = f"file records key {rec.provenance.get('iristac_key')!r}, name says {p.stem!r}"
                    elif rec.provenance.get("iristac_stage") != stage:
                        info.problem = f"file records stage {rec.provenance.get('iristac_stage')!r}, folder says {stage!r}"
                except StoreError as exc:
                    info.problem = exc.problem
                out.append(info)
            else:
                out.append(EntryInfo(p, stage, "foreign", size))
        return out

    def verify(self) -> list[EntryInfo]:
        """Fully read and validate every entry; return the bad ones."""
        return [e for e in self.entries(check=True) if e.kind == "entry" and e.problem]

    def gc(self, *, include_live: bool = False) -> list[Path]:
        """Remove temporaries left by crashed writers; return what was removed.

        A temporary whose writing process is still alive is left alone unless ``include_live``.
        Partial streamed entries (kind ``partial``: a recording's results being written, or left by
        a killed run) are kept: the next run of the same work resumes them; :meth:`clear` removes them.
        """
        removed = []
        for e in self.entries():
            if e.kind != "temp":
                continue
            m = _TEMP_RE.match(e.path.name)
            if m is None:  # an entry of kind "temp" matched this pattern when it was listed
                continue
            if not include_live and _pid_alive(int(m.group("pid"))):
                continue
            try:
                e.path.unlink()
                removed.append(e.path)
            except FileNotFoundError:
                pass
        return removed

    def clear(self, stage: str | None = None) -> list[Path]:
        """Remove entries, temporaries and quarantined files (of one stage, or all).

        Files the store did not write (names it does not use) are left in place.
        """
        removed = []
        for e in self.entries():
            if e.kind == "foreign" or (stage is not None and e.stage != stage):
                continue
            e.path.unlink(missing_ok=True)
            removed.append(e.path)
        for d in [p for p in self.root.iterdir() if p.is_dir()] if self.root.is_dir() else []:
            try:
                d.rmdir()  # only if now empty
            except OSError:
                pass
        return removed


def _pid_alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    # A zombie (killed, not yet reaped) is not writing anything.
    try:
        with open(f"/proc/{pid}/stat", encoding="ascii") as f:
            return f.read().split(")")[-1].split()[0] != "Z"
    except OSError:
        return True
