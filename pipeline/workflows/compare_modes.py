"""Compare lighting modes by reconstruction error and capture time (``iristac compare-modes``).

For each lighting mode a capture of the same contact geometry (with ground truth) is
reconstructed with every applicable solver; the result is a table of normal and depth
error, reconstruction time and capture time per mode and solver, plus the images for a
report. The captures come either from the virtual sensor (rendered from an illumination
model) or from the user's own files, as long as they carry ``truth/*`` datasets (rendered
truth, or a sphere press's truth).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from pipeline.base.errors import UserError
from pipeline.results.report import format_number

__all__ = ["ModeRun", "Comparison", "compare_captures", "compare_modes", "render_mode_captures",
           "lut_calibrations", "add_to_report", "comparison_rows", "comparison_charts", "MODE_KNOB"]

#: The knob of the benchmark rows a comparison makes (:func:`comparison_rows`).
MODE_KNOB = "lighting mode x solver"

#: Rendered ball presses a lookup table of :func:`compare_modes` is calibrated from (the full
#: demo's count; at least the quality gate's ``calibration.gate.MIN_ACCEPTED``).
LUT_PRESSES = 10


@dataclass
class ModeRun:
    """One (mode, solver) reconstruction and its figures."""

    mode: str
    solver: str
    patterns: int
    capture_seconds: float
    capture_seconds_source: str
    reconstruct_seconds: float
    normal_mean_error_deg: float | None
    normal_median_error_deg: float | None
    depth_rmse_mm: float | None
    valid_fraction: float
    images: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def to_json(self) -> dict:
        return {k: getattr(self, k) for k in ("mode", "solver", "patterns", "capture_seconds",
                                                "capture_seconds_source", "reconstruct_seconds",
                                                "normal_mean_error_deg", "normal_median_error_deg",
                                                "depth_rmse_mm", "valid_fraction")}


@dataclass
class Comparison:
    runs: list[ModeRun]
    frames: dict[str, np.ndarray] = field(default_factory=dict, repr=False)
    truth: dict[str, np.ndarray] = field(default_factory=dict, repr=False)

    def best(self) -> ModeRun | None:
        """The run with the lowest mean normal error."""
        scored = [r for r in self.runs if r.normal_mean_error_deg is not None]
        return min(scored, key=lambda r: r.normal_mean_error_deg) if scored else None

    def best_per_mode(self) -> dict[str, ModeRun]:
        out: dict[str, ModeRun] = {}
        for r in self.runs:
            if r.normal_mean_error_deg is None:
                continue
            if r.mode not in out or r.normal_mean_error_deg < out[r.mode].normal_mean_error_deg:
                out[r.mode] = r
        return out

    def to_json(self) -> dict:
        best = self.best()
        return {"runs": [r.to_json() for r in self.runs],
                "best": best.to_json() if best else None,
                "best_per_mode": {m: r.to_json() for m, r in self.best_per_mode().items()}}


def comparison_rows(runs, default: tuple[str, str] | None = None) -> list[dict]:
    """Benchmark rows (:mod:`pipeline.charts.rows`) of a comparison's runs: per mode and solver the
    mean normal error (deg) against the reconstruction seconds, with the capture seconds.

    ``runs`` are :class:`ModeRun` objects or their JSON; ``default`` is the (mode, solver) pair
    to mark as the shipped default. Runs without a normal error are left out.

    Examples
    --------
    >>> r = ModeRun("point", "nearfield", 24, 5.5, "measured", 0.4, 0.62, 0.5, 0.06, 1.0)
    >>> row = comparison_rows([r], default=("point", "nearfield"))[0]
    >>> row["setting"], row["error"], row["capture_seconds"], row["default"]
    ('point / nearfield', 0.62, 5.5, True)
    """
    rows = []
    for r in runs:
        j = r.to_json() if isinstance(r, ModeRun) else dict(r)
        if j.get("normal_mean_error_deg") is None:
            continue
        rows.append({"knob": MODE_KNOB, "setting": f"{j['mode']} / {j['solver']}", "mode": j["mode"],
                     "solver": j["solver"], "patterns": j["patterns"], "error": float(j["normal_mean_error_deg"]),
                     "error_unit": "deg", "seconds": float(j["reconstruct_seconds"]),
                     "capture_seconds": float(j["capture_seconds"]), "capture_how": j["capture_seconds_source"],
                     "depth_rmse_mm": j.get("depth_rmse_mm"), "valid_fraction": j.get("valid_fraction"),
                     "default": default is not None and (j["mode"], j["solver"]) == tuple(default)})
    return rows


def render_mode_captures(store, model, model_key, modes: Sequence[str], object: str, out: str | Path, *,
                         noise_dn: float = 1.0, camera_fps: float = 30.0, seed: int = 21, emulate: bool = False,
                         faults: str | None = None, progress: Callable[[str], None] | None = None):
    """Capture ``object`` under each mode with the virtual sensor, through the capture stage;
    write a copy of each capture to ``out/<mode>.h5``.

    With ``emulate`` the capture runs for real (:func:`pipeline.stages.capture.virtual_sensor_capture`):
    the LED-ring emulator behind a pseudo-terminal (with ``faults``), the host client over
    pyserial, and the virtual camera rendering whatever the emulated LEDs show at
    ``camera_fps``, with stale-frame flushing; the capture time is then measured (dark frame,
    a reference and a contact frame per pattern) and recorded in the capture. Without it the
    frames are rendered directly and the time is the number of frames at ``camera_fps``.

    Parameters
    ----------
    store : StageStore
    model : IlluminationModel
    model_key : StageKey or str
        The illumination's identity (its synthesize key, or its file's).
    modes : sequence of str
    object : str
        A contact object (:func:`sim.contacts.contact_surfaces`): one contact, a 2 mm
        radius pressed 0.6 mm at the centre where the object has a size.

    Returns ``(captures, capture_seconds)`` for :func:`compare_captures`.
    """
    from pipeline.base.capture import write_capture
    from pipeline.base.modes import load_mode
    from pipeline.stages import capture as capture_stage

    captures: dict[str, Path] = {}
    seconds: dict[str, tuple[float, str]] = {}
    for mode in modes:
        name = load_mode(mode).name
        section = {"mode": mode, "object": object, "contacts": 1, "size_mm": 2.0, "depth_mm": 0.6,
                   "spread_mm": 0.0, "noise_dn": float(noise_dn), "seed": int(seed), "fps": float(camera_fps)}
        if emulate:
            section.update(emulate=True, virtual_camera=True, faults=faults)
        else:
            section.update(render=True)
        rec, _, cached = capture_stage.run(store, section, model, model_key)
        if progress:
            progress(f"capture {name}: {'cached' if cached else 'captured'}")
        captures[name] = write_capture(Path(out) / f"{name}.h5", rec)
        P = rec.data["frames"].shape[1]
        if emulate:
            seconds[name] = (float(rec.meta["seconds"]),
                             f"measured, emulated ring + {camera_fps:g} fps camera, {len(rec.meta['steps'])} frames, "
                             f"{rec.meta['retries']} retries" + (" (cached)" if cached else ""))
        else:
            seconds[name] = (P / camera_fps, f"{P} frame{'s' if P > 1 else ''} at {camera_fps:g} fps")
    return captures, seconds


def lut_calibrations(store, model, modes: Sequence[str], out: str | Path, *, ball_radius_mm: float = 2.0,
                     presses=None, noise_dn: float = 1.0, bit_depth: int = 8, seed: int = 13,
                     skipped: dict[str, str] | None = None) -> dict[str, Path]:
    """A lookup-table calibration for each single-frame mode, from rendered ball presses,
    through the calibrate stage (:func:`pipeline.stages.calibrate.run`); copies go to
    ``out/calibration_<mode>.h5``.

    A mode whose calibration is refused (e.g. its channels' lights are too close to coplanar)
    gets no table; the reason goes into ``skipped`` (mode -> message) when given.
    """
    from pipeline.base.capture import write_capture
    from pipeline.base.modes import load_mode
    from pipeline.base.store import Record, write_record
    from pipeline.stages import calibrate as calibrate_stage
    from sim.rendered_capture import render_capture

    out = Path(out)
    result = {}
    for mode in modes:
        m = load_mode(mode)
        if len(m.frames) != 1:
            continue
        cap = render_capture(model, m, presses, noise_dn=noise_dn, bit_depth=bit_depth, seed=seed)
        write_capture(out / f"calibration_capture_{m.name}.h5", Record(cap.schema, cap.data, cap.meta))
        try:
            rec, _, _ = calibrate_stage.run(store, cap, ball_radius_mm=ball_radius_mm, models=["lut"])
            result[m.name] = write_record(out / f"calibration_{m.name}.h5", Record(rec.schema, rec.data, rec.meta))
        except UserError as exc:
            if skipped is not None:
                skipped[m.name] = str(exc)
    return result


def compare_captures(captures: dict[str, Any], *, illumination=None, calibrations: dict[str, Any] | None = None,
                     capture_seconds: dict[str, tuple[float, str]] | None = None, integrator: str = "dst",
                     solvers: Sequence[str] | None = None, store=None, out: str | Path | None = None,
                     progress: Callable[[str], None] | None = None) -> Comparison:
    """Reconstruct each mode's capture with each applicable solver and measure the errors.

    Parameters
    ----------
    captures : dict
        mode name -> capture path or Record (with ``truth/normals`` and ``truth/height``).
    illumination : path or Record, optional
        Illumination model for the per-pixel (near-field) light matrices; used by every
        solver except ``lut``.
    calibrations : dict, optional
        mode name -> calibration path or Record; a calibration with a lookup table enables
        the ``lut`` solver for that mode.
    capture_seconds : dict, optional
        mode name -> (seconds, how it was obtained) for the table.
    integrator : str
        Depth integrator for every run.
    solvers : sequence of str, optional
        Restrict the solvers tried.
    store : StageStore or path, optional
    out : path, optional
        Folder for per-run outputs (normals/depth files and PNGs).
    """
    from pipeline.base.store import Record, read_record
    from pipeline.normals.lights import applicable_solvers
    from pipeline.results.evaluate import angular_error_deg
    from pipeline.results.exports import depth_colormap_rgb, normal_map_rgb
    from pipeline.workflows.reconstruct import reconstruct

    if not captures:
        raise UserError("compare-modes: no captures to compare")
    calibrations = calibrations or {}
    capture_seconds = capture_seconds or {}
    runs: list[ModeRun] = []
    frames: dict[str, np.ndarray] = {}
    truth: dict[str, np.ndarray] = {}
    for mode, cap in captures.items():
        rec = cap if isinstance(cap, Record) else read_record(cap, schema="capture")
        if "truth/normals" not in rec.data:
            raise UserError(f"{rec.path}: capture of mode {mode!r} has no truth/normals; compare-modes needs "
                            f"ground truth (a rendered capture or a sphere press)")
        P = rec.data["frames"].shape[1]
        frames[mode] = rec.data["frames"][0]
        if not truth:
            truth = {"normals": rec.data["truth/normals"][0], "height": rec.data["truth/height"][0]}
        cal = calibrations.get(mode)
        cal_rec = None if cal is None else (cal if isinstance(cal, Record) else read_record(cal, schema="calibration"))
        has_lut = cal_rec is not None and any(k.startswith("models/lut/") for k in cal_rec.data)
        # The illumination gives light vectors everywhere; a calibration with a table, the table.
        kinds = {"vectors", "field"} | ({"model:lut"} if has_lut else set())
        tried = [s for s in applicable_solvers(P, rec.data["frames"].shape[-1], kinds, variants=solvers is not None)
                 if solvers is None or s in solvers]
        secs, how = capture_seconds.get(mode, (float("nan"), "not measured"))
        for solver in tried:
            if progress:
                progress(f"reconstruct {mode} / {solver}")
            kw = {"calibration": cal_rec} if solver == "lut" else {"illumination": illumination}
            run_out = Path(out) / f"{mode}-{solver}" if out is not None else None
            t0 = time.perf_counter()
            res = reconstruct(rec, solver=solver, integrator=integrator, store=store, out=run_out, images=False,
                              force=True, **kw)
            dt = time.perf_counter() - t0
            n = res.normals.data["normals"][0]
            m = res.normals.data["mask"][0].astype(bool)
            gt = rec.data["truth/normals"][0]
            err = angular_error_deg(n, gt)
            err_valid = err[m] if m.any() else np.array([np.nan])
            height = res.depth.data["height"][0]
            runs.append(ModeRun(
                mode=mode, solver=solver, patterns=P, capture_seconds=float(secs), capture_seconds_source=how,
                reconstruct_seconds=dt,
                normal_mean_error_deg=res.summary.get("normal_mean_error_deg"),
                normal_median_error_deg=float(np.median(err_valid)) if m.any() else None,
                depth_rmse_mm=res.summary.get("depth_rmse_mm"),
                valid_fraction=float(m.mean()),
                images={"normals": normal_map_rgb(n, m),
                        "depth": depth_colormap_rgb(height, m),
                        "error": _error_map(err, m)},
            ))
    return Comparison(runs, frames, truth)


def _error_map(err_deg: np.ndarray, mask: np.ndarray, vmax: float = 10.0) -> np.ndarray:
    """Angular error as an RGB image: black = 0, white = ``vmax`` degrees or more, masked = blue."""
    e = np.clip(np.nan_to_num(err_deg, nan=vmax) / vmax, 0.0, 1.0)
    img = np.stack([e, e, e], axis=-1)
    img[~mask] = (0.1, 0.1, 0.5)
    return img


def _display_frame(frame: np.ndarray) -> np.ndarray:
    """A capture frame (H, W, 3) or the mean of a pattern stack (P, H, W, 3) for display."""
    f = np.asarray(frame, dtype=np.float64)
    if f.ndim == 4:
        f = f.mean(axis=0)
    top = np.percentile(f, 99.5) or 1.0
    return np.clip(f / top, 0.0, 1.0)


def comparison_charts(comp: Comparison, default: tuple[str, str] | None = None) -> list:
    """The comparison's error-against-time charts (:mod:`pipeline.charts`): normal error against
    capture time and against reconstruction time, per mode and solver, the same charts as
    ``iristac bench modes`` draws."""
    from pipeline.charts.decisions import build_charts

    return build_charts(comparison_rows(comp.runs, default))


def add_to_report(report, comp: Comparison, title: str = "Lighting modes compared",
                  default: tuple[str, str] | None = None) -> None:
    """Add the comparison's charts, table and images to a :class:`pipeline.results.report.Report`."""
    from pipeline.results.exports import depth_colormap_rgb, normal_map_rgb

    s = report.section(title, "Normal error is the mean angle between reconstructed and true normals over the "
                              "pixels each solver marked valid; depth RMSE is over the whole image. Capture time "
                              "is how long the capture of one contact took, with how it was obtained.")
    header = ["mode", "solver", "patterns", "normal mean (deg)", "normal median (deg)", "depth RMSE (mm)",
              "valid", "reconstruct (s)", "capture (s)"]
    rows = [[r.mode, r.solver, r.patterns, format_number(r.normal_mean_error_deg),
             format_number(r.normal_median_error_deg), format_number(r.depth_rmse_mm), f"{100 * r.valid_fraction:.1f}%", r.reconstruct_seconds,
             f"{r.capture_seconds:.3g} ({r.capture_seconds_source})"] for r in comp.runs]
    for chart in comparison_charts(comp, default):
        s.chart(chart)
    s.table(header, rows)
    best = comp.best()
    if best is not None:
        s.paragraph(f"Lowest normal error: {best.mode} with {best.solver} "
                    f"({best.normal_mean_error_deg:.3g} deg, depth RMSE {format_number(best.depth_rmse_mm)} mm).")
    if comp.truth:
        t = report.section("Ground truth")
        t.image("true normals", normal_map_rgb(comp.truth["normals"]))
        t.image("true depth", depth_colormap_rgb(comp.truth["height"]))
    for mode, frame in comp.frames.items():
        ms = report.section(f"Mode: {mode}")
        ms.image(f"{mode}: captured frame" + (" (mean of patterns)" if frame.shape[0] > 1 else ""),
                 _display_frame(frame if frame.shape[0] > 1 else frame[0]))
        for r in comp.runs:
            if r.mode != mode:
                continue
            ms.image(f"{mode}/{r.solver}: normals", r.images["normals"])
            ms.image(f"{mode}/{r.solver}: depth", r.images["depth"])
            ms.image(f"{mode}/{r.solver}: error (white = 10 deg)", r.images["error"])



def compare_modes(out: str | Path, *, modes: Sequence[str] | None = None, scene: str = "default",
                  illumination: str | Path | None = None, object: str = "test-object",
                  shape: tuple[int, int] = (120, 160), mm_per_px: float = 0.15, rays: int = 2_000_000,
                  captures: dict[str, str] | None = None, calibrations: dict[str, str] | None = None,
                  lut: bool = True, integrator: str = "dst", cache: str | Path | None = None,
                  noise_dn: float = 1.0, camera_fps: float = 30.0, emulate: bool = True,
                  faults: str | None = None, log: Callable[[str], None] | None = None) -> dict:
    """Which lighting mode reconstructs best, at what capture time (``iristac compare-modes``).

    Either the user's own ``captures`` (mode -> capture.h5 with ``truth/*``) are compared, or
    the virtual sensor renders ``object`` under each of ``modes`` from an illumination model
    (``illumination`` file, else ``scene`` traced with ``rays`` rays per LED), captured through
    the ring emulator and virtual camera when ``emulate`` (see :func:`render_mode_captures`).
    The trace, the captures, the lookup-table calibrations and the reconstructions go through
    the stage registry (:mod:`pipeline.stages`) and the store in ``cache``. Writes
    ``report.html`` and ``report.json`` into ``out`` and returns the JSON.
    """
    from pipeline.base.identity import record_key
    from pipeline.base.modes import list_modes
    from pipeline.base.store import StageStore, read_record
    from pipeline.results.report import Report
    from pipeline.stages import synthesize as synthesize_stage
    from pipeline.stages.synthesize import illumination_model
    from sim.rendered_capture import press_ring, sphere_presses

    say = log or (lambda m: None)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    store = StageStore(cache if cache is not None else out / "cache")
    t0 = time.perf_counter()
    ill_path = None
    model = None
    key = None
    if illumination is not None:
        ill_path = Path(illumination)
        if not ill_path.is_file():
            raise UserError(f"--illumination {ill_path}: no such file")
        ill_rec = read_record(ill_path, schema="illumination")
        model, key = illumination_model(ill_rec), record_key(ill_rec)
    elif not captures:
        say(f"tracing scene {scene!r}: {rays:,} rays per LED onto {shape}")
        model, key, _ = synthesize_stage.run(store, scene, shape, mm_per_px, rays=rays, sampler="sobol")
        ill_path = store.path_for(key)
    cals: dict[str, Any] = dict(calibrations or {})
    lut_skipped: dict[str, str] = {}
    if captures:
        caps: dict[str, Any] = dict(captures)
        seconds = {}
        for m, p in caps.items():
            rec = read_record(p, schema="capture")
            secs = rec.meta.get("seconds")
            seconds[m] = (float(secs), "measured") if secs is not None else (float("nan"), "not recorded")
    else:
        modes = list(modes or list_modes())
        say(f"capturing the {object} object under {', '.join(modes)}")
        caps, seconds = render_mode_captures(store, model, key, modes, object, out / "captures", noise_dn=noise_dn,
                                             camera_fps=camera_fps, emulate=emulate, faults=faults)
        if lut:
            say("calibrating lookup tables for the single-frame modes")
            # The demo's layout and count: the calibrate stage's quality gate refuses fewer
            # accepted presses than calibration.gate.MIN_ACCEPTED (5 lost every table).
            depths, centres = press_ring(model.shape, model.mm_per_px, LUT_PRESSES)
            presses = sphere_presses(model.shape, model.mm_per_px, 2.0, depths, centres)
            for m, p in lut_calibrations(store, model, modes, out, presses=presses, noise_dn=noise_dn,
                                         skipped=lut_skipped).items():
                cals.setdefault(m, p)
            for m, why in lut_skipped.items():
                say(f"no lookup table for {m}: {why}")
    comp = compare_captures(caps, illumination=ill_path, calibrations=cals, capture_seconds=seconds,
                            integrator=integrator, store=store, out=out / "runs", progress=say)
    data = {"comparison": comp.to_json(), "seconds": time.perf_counter() - t0,
            "illumination": str(ill_path) if ill_path else None, "lut_skipped": lut_skipped}
    report = Report("IrisTac: lighting modes compared")
    add_to_report(report, comp)
    for m, why in lut_skipped.items():
        report.sections[0].paragraph(f"No lookup table for {m}: {why}")
    report.write(out, data=data)
    return data
