"""``iristac bench all``: run every benchmark, write ``docs/benchmarks.md`` and an error-vs-time plot.

Each benchmark module returns a dict; where it has ``"rows"`` — a list of dicts with
``knob``, ``setting``, ``seconds`` and optionally ``error`` and ``error_unit`` — those rows
go into one table and one plot (one panel per knob: error against seconds, so what accuracy
costs in time is visible at a glance). Every row records the machine it ran on. A benchmark
without rows contributes its own table verbatim.
"""

from __future__ import annotations

import importlib
import os
import platform
import time
from pathlib import Path
from typing import Any

from pipeline.report import format_number

BENCHES = ["sim", "render", "capture", "reconstruct", "calibration", "live", "modes"]


def add_arguments(parser) -> None:
    parser.add_argument("--out", default="docs/benchmarks.md", help="markdown report to write")
    parser.add_argument("--plot", default="docs/benchmarks.png", help="error-vs-time plot to write")
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
    out = {"machine": machine, "quick": bool(getattr(args, "quick", False)), "sections": sections}
    if args.out:
        import json

        raw = Path(args.out).with_suffix(".json")
        raw.parent.mkdir(parents=True, exist_ok=True)
        raw.write_text(json.dumps(out, indent=1, default=str), encoding="utf-8")
    md = format_markdown(out, plot_name=Path(args.plot).name if args.plot else None)
    if args.out:
        Path(args.out).parent.mkdir(parents=True, exist_ok=True)
        Path(args.out).write_text(md, encoding="utf-8")
        out["markdown"] = str(args.out)
    if args.plot:
        plot_rows([r for s in sections for r in s["rows"]], args.plot)
        out["plot"] = str(args.plot)
    return out


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
            rows.append({"knob": f"lens design: {what} error (rays x sampler)", "setting": f"{r['sampler']} {r['rays']:,}",
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



def format_markdown(result: dict, plot_name: str | None = None) -> str:
    lines = ["# Benchmarks", "",
             "Written by `iristac bench all`" + (" --quick" if result.get("quick") else "") + ". "
             "Every figure below was measured by that command on the machine named in its row; "
             "error and time sit side by side so that what accuracy costs in time is visible.", "",
             f"Machine: {result['machine']}", ""]
    if plot_name:
        lines += [f"![error against time for every knob]({plot_name})", ""]
    for s in result["sections"]:
        lines += [f"## {s['bench']}", "", f"(benchmark ran for {s['seconds']:.1f} s)", ""]
        if s["error"]:
            lines += [f"**failed**: `{s['error']}`", ""]
            continue
        if s["rows"]:
            lines += ["| knob | setting | error | seconds | machine |", "|---|---|---|---|---|"]
            for r in s["rows"]:
                err = format_number(r.get("error"))
                if r.get("error") is not None and r.get("error_unit"):
                    err += f" {r['error_unit']}"
                lines.append(f"| {r['knob']} | {r['setting']} | {err} | {format_number(r.get('seconds'))} | {r['machine']} |")
            lines.append("")
        if s["table"]:
            lines += ["```", s["table"].rstrip(), "```", ""]
    return "\n".join(lines)


def plot_rows(rows: list[dict], path: str) -> None:
    """One panel per knob: error against seconds, each setting labelled."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    by_knob: dict[str, list[dict]] = {}
    for r in rows:
        if r.get("error") is not None and r.get("seconds") is not None:
            by_knob.setdefault(f"{r['bench']}: {r['knob']}", []).append(r)
    n = max(1, len(by_knob))
    cols = min(3, n)
    nrows = (n + cols - 1) // cols
    fig, axes = plt.subplots(nrows, cols, figsize=(5 * cols, 3.6 * nrows), squeeze=False)
    for ax, (knob, rs) in zip(axes.flat, sorted(by_knob.items())):
        xs = [max(float(r["seconds"]), 1e-6) for r in rs]
        ys = [max(float(r["error"]), 1e-12) for r in rs]
        ax.scatter(xs, ys)
        for x, y, r in zip(xs, ys, rs):
            ax.annotate(str(r["setting"]), (x, y), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        if min(ys) > 0 and max(ys) / min(ys) > 20:
            ax.set_yscale("log")
        unit = rs[0].get("error_unit") or ""
        ax.set_title(knob, fontsize=9)
        ax.set_xlabel("seconds")
        ax.set_ylabel(f"error {unit}".strip())
        ax.grid(True, alpha=0.3)
    for ax in list(axes.flat)[len(by_knob):]:
        ax.axis("off")
    if not by_knob:
        axes.flat[0].text(0.5, 0.5, "no benchmark reported error and time", ha="center")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)


def format_table(result: dict) -> str:
    lines = [f"machine: {result['machine']}"]
    for s in result["sections"]:
        state = "FAILED: " + s["error"] if s["error"] else f"{len(s['rows'])} rows"
        lines.append(f"{s['bench']:<12} {s['seconds']:>7.1f} s  {state}")
    if result.get("markdown"):
        lines.append(f"wrote {result['markdown']}" + (f" and {result['plot']}" if result.get("plot") else ""))
    return "\n".join(lines)
