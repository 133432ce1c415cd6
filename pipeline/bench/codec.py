"""``iristac bench codec``: how to store the frames of captures and recordings, by measurement.

For each candidate layout of a ``frames (K, P, H, W, C)`` stack (chunks of one frame set each):

- ``lzf`` (the stage store's LZF, shuffle and Fletcher-32, one image a chunk: how captures were
  written before the frames layout),
- ``raw`` (unfiltered chunks, read by file offsets),
- ``zstd:3``, ``zstd:1``, ``zstd:-1``, ``zstd:-3`` (the frames layout of
  :mod:`pipeline.base.frame_codec` at four levels: one Zstandard frame per chunk with its
  checksum, compressed on several threads, decoded on the reader's; the negative ("fast")
  levels leave literals without entropy coding: larger, faster to decode),
- ``hdf5plugin-zstd`` (the same filter written through HDF5: one thread, no checksum),
- ``blosc2-lz4``, ``blosc2-zstd`` (Blosc2 through ``hdf5plugin``, byte shuffle and bit shuffle),
- ``lz4`` (``hdf5plugin``'s LZ4 filter),

on real frames (``shared/data``: the GelSight npz through :func:`calibration.importers.load_gelsight_npz`,
the DIGIT JPEG folder through :func:`calibration.image_import.read_image`) and on a virtual
sensor's presses (:func:`sim.virtual_sensor.render_sensor`, what ``iristac sim sensor --seed 1
--shape 240 320`` writes): the stored size over the raw size, write MB/s (file created, chunks
written, closed; page cache, no fsync), and decode GB/s of the raw bytes read back into a
caller's buffer the way ``batch`` reads (runs of :data:`BATCH` frame sets in order,
:class:`pipeline.base.h5frames.H5Frames`) on one thread and on every core, and through HDF5's
own filter pipeline (``Dataset.read_direct``, what ``read_record`` gets). Every read is
compared with the frames written (``exact``). Files are just written (in the page cache): the
figures are decode costs, not disk speeds. Best of ``--repeats`` runs.
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path
from typing import Any, Callable

import numpy as np

#: Frame sets per read (the read pattern of ``batch``).
BATCH = 64
#: Where the real frames are (``shared/data`` beside the checkout).
DATA = Path(__file__).resolve().parents[2].parent / "shared" / "data"


def add_arguments(parser) -> None:
    parser.add_argument("--data", default=str(DATA), help="folder of the real frames (default: shared/data)")
    parser.add_argument("--presses", type=int, default=200, help="virtual sensor presses (frame sets; default 200)")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats of each read and write (best kept)")
    parser.add_argument("--threads", type=int, default=0, help="reader threads of the many-thread column "
                                                               "(default: every core)")
    parser.add_argument("--codecs", default="", help="comma-separated subset of the candidates (default: all)")


def _candidates() -> dict[str, tuple[Callable[[Any, np.ndarray], None], str]]:
    """name -> (writer ``(h5 file, frames)``, what it is)."""
    import hdf5plugin

    from pipeline.base.frame_codec import write_frames

    def chunked(**kw):
        return lambda f, a: f.create_dataset("frames", data=a, chunks=(1,) + a.shape[1:], **kw)

    return {
        # the stage store's settings for a large dataset (pipeline.base.store: one image a chunk)
        "lzf": (lambda f, a: f.create_dataset("frames", data=a, chunks=(1,) * (a.ndim - 3) + a.shape[-3:],
                                              compression="lzf", shuffle=True, fletcher32=True),
                "LZF + shuffle + Fletcher-32, an image a chunk (before)"),
        "raw": (chunked(), "unfiltered chunks, read by file offsets"),
        **{f"zstd:{lvl}": (lambda f, a, lvl=lvl: write_frames(f, "frames", a, level=lvl),
                           f"Zstandard level {lvl} + XXH64, one frame set a chunk, decoded on threads")
           for lvl in (3, 1, -1, -3)},
        "hdf5plugin-zstd": (chunked(**hdf5plugin.Zstd(clevel=1)), "hdf5plugin.Zstd level 1 written by HDF5"),
        "blosc2-lz4": (chunked(**hdf5plugin.Blosc2(cname="lz4", clevel=5, filters=hdf5plugin.Blosc2.SHUFFLE)),
                       "Blosc2 LZ4 level 5, byte shuffle"),
        "blosc2-zstd": (chunked(**hdf5plugin.Blosc2(cname="zstd", clevel=1, filters=hdf5plugin.Blosc2.BITSHUFFLE)),
                        "Blosc2 Zstd level 1, bit shuffle"),
        "lz4": (chunked(**hdf5plugin.LZ4()), "hdf5plugin.LZ4 (HDF5's LZ4 filter)"),
    }


def frame_sets(data: Path, presses: int, quick: bool) -> tuple[dict[str, np.ndarray], list[str]]:
    """The stacks measured, ``(K, P, H, W, C)`` uint8 each, and notes on what was left out."""
    from sim.virtual_sensor import CONTACT_LOOK_EFFECTS, SENSOR_EFFECTS, random_sensor, render_sensor

    out: dict[str, np.ndarray] = {}
    notes: list[str] = []
    npz = data / "gelsight_ball_presses.npz"
    if npz.is_file():
        from calibration.importers import load_gelsight_npz

        out["gelsight 160x120"] = np.ascontiguousarray(load_gelsight_npz(npz).frames)
    else:
        notes.append(f"gelsight: left out ({npz} not found)")
    digit = data / "digit_ball_presses"
    files = sorted(digit.glob("frame_*.jpg"), key=lambda p: int(p.stem.split("_")[1])) if digit.is_dir() else []
    if files:
        from calibration.image_import import read_image

        files = files[:8] if quick else files
        out["digit 480x640"] = np.ascontiguousarray(np.stack([read_image(p) for p in files])[:, None])
    else:
        notes.append(f"digit: left out ({digit} has no frame_*.jpg)")
    n = min(presses, 16) if quick else presses
    # The camera's flaws only (markers, vignetting, drift, stripes, noise, JPEG): the frames these
    # figures were first measured on, so they stay comparable from run to run.
    flaws = [e for e in SENSOR_EFFECTS if e not in CONTACT_LOOK_EFFECTS + ("rim_smoothing", "optical_blur")]
    out["virtual 320x240"] = np.ascontiguousarray(
        render_sensor(random_sensor(1, shape=(240, 320), num_presses=n, effects=flaws)).capture.frames)
    return out, notes


def _best(fn: Callable[[], Any], repeats: int) -> float:
    best = float("inf")
    for _ in range(max(1, repeats)):
        t = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t)
    return best


def measure(name: str, writer, frames: np.ndarray, folder: Path, threads: int, repeats: int) -> dict:
    """One candidate on one stack: size, write and decode speeds, exactness."""
    from pipeline.base.frame_codec import h5py_with_filters
    from pipeline.base.h5frames import H5Frames

    h5py = h5py_with_filters()
    path = folder / f"{name}.h5"

    def write():
        with h5py.File(path, "w", libver="latest") as f:
            writer(f, frames)

    write_s = _best(write, repeats)
    with h5py.File(path, "r") as f:
        stored = int(f["frames"].id.get_storage_size())
    nbytes = frames.nbytes
    dst = np.empty_like(frames)
    row: dict[str, Any] = {"codec": name, "frames": int(len(frames)), "mb": nbytes / 1e6, "ratio": stored / nbytes,
                           "write_mb_s": nbytes / write_s / 1e6}
    exact = True
    for label, n in (("decode_1", 1), ("decode_n", threads)):
        with H5Frames(path, "frames", threads=n) as src:
            row["path"] = "threads" if src.direct else "HDF5 filters"

            def read(src=src):
                for a in range(0, len(src), BATCH):
                    b = min(len(src), a + BATCH)
                    src.read_into(dst[a:b], a, b)

            dst[:] = 0
            read()  # warm: page cache, thread pool, decompressor contexts
            exact &= bool(np.array_equal(dst, frames))
            row[f"{label}_gb_s"] = nbytes / _best(read, repeats) / 1e9
    with h5py.File(path, "r", rdcc_nbytes=0) as f:  # no chunk cache: a small stack would be decoded once
        ds = f["frames"]
        ds.read_direct(dst)
        row["hdf5_gb_s"] = nbytes / _best(lambda: ds.read_direct(dst), repeats) / 1e9
        exact &= bool(np.array_equal(dst, frames))
    row["exact"] = exact
    row["us_per_frame_n"] = nbytes / len(frames) / (row["decode_n_gb_s"] * 1e9) * 1e6
    path.unlink()
    return row


def run(args) -> dict:
    quick = bool(getattr(args, "quick", False))
    repeats = 1 if quick else int(getattr(args, "repeats", 3))
    threads = int(getattr(args, "threads", 0)) or (os.cpu_count() or 1)
    cands = _candidates()
    wanted = [c.strip() for c in str(getattr(args, "codecs", "") or "").split(",") if c.strip()]
    unknown = [c for c in wanted if c not in cands]
    if unknown:
        from pipeline.base.errors import UserError

        raise UserError(f"bench codec: unknown codec {', '.join(unknown)} (candidates: {', '.join(cands)})")
    names = wanted or list(cands)
    stacks, notes = frame_sets(Path(getattr(args, "data", DATA)), int(getattr(args, "presses", 200)), quick)
    load = list(os.getloadavg())
    results = []
    with tempfile.TemporaryDirectory(prefix="iristac-bench-codec-") as d:
        for label, frames in stacks.items():
            for name in names:
                writer, _ = cands[name]
                results.append({"frames_of": label, "frame_kb": frames[0].nbytes / 1e3,
                                **measure(name, writer, frames, Path(d), threads, repeats)})
    from pipeline.base.frame_codec import FRAMES_CODEC, ZSTD_LEVEL

    chosen = f"{FRAMES_CODEC}:{ZSTD_LEVEL}" if FRAMES_CODEC == "zstd" else FRAMES_CODEC
    rows = [{"knob": f"frames codec: decode a frame set ({r['frames_of']}, {threads} threads)", "setting": r["codec"],
             # the size as the "error" (lower is better): the charts then show size against decode time
             "seconds": r["us_per_frame_n"] * 1e-6, "error": r["ratio"], "error_unit": "stored / raw size",
             "default": r["codec"] == chosen} for r in results]
    return {"threads": threads, "repeats": repeats, "batch": BATCH, "quick": quick, "notes": notes,
            "descriptions": {n: cands[n][1] for n in names}, "chosen": chosen,
            "load_average": load + list(os.getloadavg()), "results": results, "rows": rows,
            "exit_code": 0 if all(r["exact"] for r in results) else 1}


def format_table(result: dict) -> str:
    n = result["threads"]
    head = (f"{'frames':<17} {'codec':<16} {'ratio':>6} {'write MB/s':>10} {'1 thr GB/s':>10} "
            f"{f'{n} thr GB/s':>10} {'HDF5 GB/s':>9} {'us/frame':>8} {'read by':<13} {'exact':<5}")
    lines = [f"frames stored in chunks of one frame set; decode = read back into a caller's buffer, {result['batch']} "
             f"frame sets a call, in order (H5Frames), on 1 and {n} threads, and through HDF5's filters "
             f"(read_direct, one thread); page cache; best of {result['repeats']}; ratio = stored / raw; "
             f"us/frame = decode of one frame set on {n} threads",
             *result.get("notes", []), head, "-" * len(head)]
    for r in result["results"]:
        mark = "*" if r["codec"] == result.get("chosen") else " "
        lines.append(f"{r['frames_of']:<17} {r['codec'] + mark:<16} {r['ratio']:>6.3f} {r['write_mb_s']:>10.0f} "
                     f"{r['decode_1_gb_s']:>10.2f} {r['decode_n_gb_s']:>10.2f} {r['hdf5_gb_s']:>9.2f} "
                     f"{r['us_per_frame_n']:>8.0f} {r['path']:<13} {'yes' if r['exact'] else 'NO':<5}")
    lines.append("* the layout captures and recordings write (pipeline/base/frame_codec.py)")
    for name, text in result.get("descriptions", {}).items():
        lines.append(f"  {name:<16} {text}")
    if result.get("load_average"):
        la = result["load_average"]
        lines.append(f"load average {la[0]:.2f} at the start, {la[3]:.2f} at the end")
    return "\n".join(lines)
