"""``iristac bench all``: run every benchmark; write the figures and their charts into ``docs/``.

Each benchmark module returns a dict; where it has ``"rows"`` (dicts with ``knob``,
``setting``, ``seconds``, optionally ``error``, ``error_unit`` and the fields
:mod:`pipeline.charts.rows` lists) those rows are the run's data. Every row records the
machine it ran on. A benchmark without rows contributes its own table verbatim. Written,
beside ``--out`` (``docs/benchmarks.md``):

- ``benchmarks.json``: the run (the single source of every chart; ``iristac bench report``
  and ``iristac bench compare`` read it);
- ``benchmarks.html``: the interactive page (:mod:`pipeline.bench.report`);
- ``--plot`` (``docs/benchmarks.png``): the summary figure, six panels, 900 px wide;
- ``images/benchmarks/KEY.png``: one chart per decision, shown in the markdown with the
  sentence under each.
"""

from __future__ import annotations

import importlib
import os
import platform
import time
from pathlib import Path
from typing import Any

from pipeline.bench.report import write_docs

BENCHES = ["sim", "render", "capture", "codec", "reconstruct", "calibration", "live", "batch", "modes"]


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="docs/benchmarks.md", help="markdown report to write")
    parser.add_argument("--plot", default=None,
                        help="summary figure to write (six error-against-time panels, 900 px wide; default: "
                             "beside --out, same name, .png)")
    parser.add_argument("--only", nargs="*", choices=BENCHES, help="run only these benchmarks")


def machine_description() -> str:
    """A one-line description of this machine: CPU model, cores, memory, torch and device.

    Examples
    --------
    >>> "cores" in machine_description()
    True
    """
    cpu = platform.processor() or platform.machine()
    try:
        with open("/proc/cpuinfo", encoding="ascii", errors="replace") as f:
            for line in f:
                if line.startswith("model name"):
                    cpu = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    mem = ""
    try:
        pages = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        mem = f", {pages / 2**30:.0f} GiB"
    except (ValueError, OSError):
        pass
    try:
        import torch

        dev = f"torch {torch.__version__}, " + ("cuda " + torch.cuda.get_device_name(0) if torch.cuda.is_available() else "cpu")
    except Exception:  # noqa: BLE001 - the description must never fail
        dev = "no torch"
    return f"{cpu}, {os.cpu_count()} cores{mem}, {dev}"


def run(args) -> dict:
    names = args.only or BENCHES
    machine = machine_description()
    load = list(os.getloadavg())
    sections: list[dict[str, Any]] = []
    for name in names:
        t0 = time.perf_counter()
        try:
            module = importlib.import_module(f"pipeline.bench.{name}")
        except ModuleNotFoundError:
            sections.append({"bench": name, "seconds": 0.0, "rows": [], "table": None,
                             "error": "not implemented yet"})
            continue
        try:
            result = module.run(_sub_args(module, args))
            error = None
        except Exception as exc:  # noqa: BLE001 - one failing benchmark must not hide the others
            result, error = {}, f"{type(exc).__name__}: {exc}"
        seconds = time.perf_counter() - t0
        rows = [dict(r, bench=name, machine=machine) for r in common_rows(name, result)] if not error else []
        # A benchmark without common rows also contributes its own table (the ray tracer's has
        # throughput and memory figures that are not error/time pairs).
        table = module.format_table(result) if not error and not result.get("rows") else None
        sections.append({"bench": name, "seconds": seconds, "rows": rows, "table": table, "error": error})
    out = {"machine": machine, "quick": bool(getattr(args, "quick", False)),
           "load_average": load + list(os.getloadavg()), "sections": sections}
    if args.out:
        # The figure goes beside the report unless asked elsewhere: a report written to a
        # scratch folder must not overwrite docs/benchmarks.png.
        _write_outputs(out, Path(args.out), args.plot or str(Path(args.out).with_suffix(".png")))
    elif args.plot:
        from pipeline.bench.report import write_summary
        from pipeline.charts.decisions import overview
        from pipeline.charts.rows import result_rows

        out["plot"] = write_summary(overview(result_rows(out)), args.plot)["path"]
    return out


def _write_outputs(out: dict, md_path: Path, plot: str | None) -> None:
    import json

    md_path.parent.mkdir(parents=True, exist_ok=True)
    raw = md_path.with_suffix(".json")
    raw.write_text(json.dumps(out, indent=1, default=str), encoding="utf-8")
    write_docs(out, md_path, plot)


def common_rows(name: str, result: dict) -> list[dict]:
    """The ``rows`` of a benchmark result, mapping sectioned results (the ray tracer's) too."""
    if result.get("rows"):
        return list(result["rows"])
    if name != "sim":
        return []
    rows = []

    def finite(v):
        return None if v is None or v != v else float(v)

    def kept(r, *keys):
        return {k: r[k] for k in keys if k in r}

    for r in result.get("rays_sampler", {}).get("rows", []):
        rows.append({"knob": "rays x sampler", "setting": f"{r['sampler']} {r['rays']:,}",
                     "error": finite(r["image_error"]), "error_unit": "rel. L2 vs reference", "seconds": r["seconds"],
                     **kept(r, "sampler", "rays", "seconds_runs", "default")})
    flux = result.get("flux", {})
    for what, key in (("flux", "flux_error_pct"), ("uniformity", "cv_error_pct")):
        for r in flux.get("rows", []):
            rows.append({"knob": f"lens design: {what} error (rays x sampler)",
                         "setting": f"{r['sampler']} {r['rays']:,}",
                         "error": finite(r[key]), "error_unit": "% (RMS over seeds)", "seconds": r["seconds"],
                         "error_runs": r[key.replace("_pct", "s_pct")],
                         **kept(r, "sampler", "rays", "seeds", "seconds_runs", "default")})
    for r in result.get("newton", {}).get("rows", []):
        rows.append({"knob": f"intersection iterations ({r['dtype']})", "setting": f"{r['method']} x{r['iterations']}",
                     "error": finite(r["median_error_mm"]), "error_unit": "mm (median)", "seconds": r["seconds"],
                     **kept(r, "seconds_runs", "default")})
    for r in result.get("multi_source", {}).get("rows", []):
        rows.append({"knob": "multi-source method", "setting": r["method"], "error": finite(r["sum_error"]),
                     "error_unit": "rel. error of the 24-LED image", "seconds": r["seconds"],
                     **kept(r, "seconds_runs", "default")})
    for r in result.get("effects", {}).get("rows", []):
        rows.append({"knob": "effect set", "setting": r["effects"], "error": None, "seconds": r["seconds"]})
    return rows


def _sub_args(module, args):
    """The namespace a single benchmark would get from ``iristac bench NAME``, with defaults."""
    import argparse

    p = argparse.ArgumentParser()
    p.add_argument("--json", action="store_true")
    p.add_argument("--quick", action="store_true")
    if hasattr(module, "add_arguments"):
        module.add_arguments(p)
    ns = p.parse_args(["--quick"] if getattr(args, "quick", False) else [])
    return ns



def format_table(result: dict) -> str:
    lines = [f"machine: {result['machine']}"]
    for s in result["sections"]:
        state = "FAILED: " + s["error"] if s["error"] else f"{len(s['rows'])} rows"
        lines.append(f"{s['bench']:<12} {s['seconds']:>7.1f} s  {state}")
    if result.get("markdown"):
        lines.append(f"wrote {result['markdown']}, {result['json']}, {result['page']}"
                     + (f" and {result['plot']}" if result.get("plot") else ""))
    if result.get("load_average"):
        la = result["load_average"]
        lines.append(f"load average {la[0]:.2f} at the start, {la[3]:.2f} at the end")
    return "\n".join(lines)
