"""The five stages of ``iristac run`` as a :mod:`pipeline.orchestrate` graph built from a config.

:func:`resolve_config` fills every default and turns relative paths into absolute ones, so a
stage's parameters are exactly what changes its result (writing a default out explicitly, or
moving the config file, does not recompute anything). :func:`build_stages` maps the sections
present in the config to :class:`~pipeline.orchestrate.Stage` objects calling the real stage
functions:

============  =====================================================  ==========================
stage         computation                                            reads
============  =====================================================  ==========================
synthesize    ``sim.synthesize.synthesize_record`` (``traced``) or   --
              :func:`sim.render.bare_ring_illumination`
calibrate     :func:`calibration.calibrate.calibrate` on a capture   synthesize (``render``) or
              file or on a sphere capture rendered from the          a file's content hash
              synthesized illumination
capture       a capture file, :func:`sim.rendered_capture.render_    synthesize (virtual) or a
              capture`, the ring emulator + rendering virtual        file's content hash
              camera (:func:`virtual_sensor_capture`), or hardware
              (:func:`pipeline.capture.session.capture`)
normals       :func:`pipeline.reconstruct.normals_record`            capture, calibrate or
                                                                     synthesize
depth         :func:`pipeline.reconstruct.depth_record`              normals
============  =====================================================  ==========================

Stages whose section is absent are skipped; a stage that needs an absent one says so.

Examples
--------
>>> cfg = resolve_config({"synthesize": {"model": "bare_ring", "height": 8, "width": 10},
...                       "capture": {"render": True, "contacts": 1}, "normals": {}, "depth": {}})
>>> [s.name for s in build_stages(cfg)]
['synthesize', 'capture', 'normals', 'depth']
>>> cfg["normals"]["lights"], cfg["capture"]["mode"]
('illumination', 'monochromatic')
"""

from __future__ import annotations

import copy
import os
import tempfile
from pathlib import Path
from typing import Any, Callable, Mapping

import numpy as np

from pipeline.errors import UserError
from pipeline.orchestrate import Stage, file_input_key

__all__ = ["STAGE_ORDER", "DEFAULTS", "resolve_config", "build_stages", "contact_surfaces", "illumination_record",
           "illumination_model", "virtual_sensor_capture"]

#: Stage names in the order they run.
STAGE_ORDER = ("synthesize", "calibrate", "capture", "normals", "depth")

#: Defaults filled in by :func:`resolve_config` (per section; ``None`` = no default).
DEFAULTS: dict[str, dict[str, Any]] = {
    # rays, sampler and seed of a traced model default to the scene's ``trace`` section.
    "synthesize": {"model": "traced", "scene": "default", "method": "hits", "gel_z": 35.0, "height": 60,
                   "width": 80, "mm_per_px": 0.5},
    "calibrate": {"ball_radius_mm": 4.0, "model": "far", "folds": 5},
    "calibrate.render": {"presses": 8, "depth_mm": 0.6, "spread_mm": 4.0, "noise_dn": 1.0, "target_dn": 200.0,
                         "seed": 0},
    "capture": {"mode": "monochromatic", "object": "sphere", "size_mm": 3.0, "depth_mm": 0.5, "contacts": 2,
                "spread_mm": 3.0, "noise_dn": 1.0, "target_dn": 200.0, "seed": 0, "fps": 100.0,
                "frames_per_pattern": 1, "mm_per_px": 0.1},
    "normals": {"solver": "lstsq", "ratio": False, "max_condition": 1e3, "dtype": "float32"},
    "depth": {"integrator": "dst"},
}

# Stage versions: bump when a computation here changes its result.
_VERSIONS = {"calibrate": 1, "capture": 1}


# ---------------------------------------------------------------------------------------------
# Config

def _abs(path: str, base: Path) -> str:
    p = Path(os.path.expanduser(path))
    return str(p if p.is_absolute() else (base / p).resolve())


def _capture_mode(cfg: Mapping[str, Any], base: Path) -> str:
    """The lighting mode of the capture stage (a capture file's own ``mode`` attribute)."""
    cap = cfg.get("capture") or {}
    if cap.get("file"):
        from pipeline.store import StoreError, read_record

        try:
            mode = read_record(_abs(cap["file"], base), schema="capture", load=False).meta.get("mode")
        except StoreError:
            mode = None  # the capture stage reports the bad file when it runs
        if mode:
            return str(mode)
    return cap.get("mode", DEFAULTS["capture"]["mode"])


def resolve_config(config: Mapping[str, Any], base_dir: str | os.PathLike = ".", source: str = "<config>"
                   ) -> dict[str, Any]:
    """Validate a parsed pipeline config, fill defaults and make paths absolute.

    Parameters
    ----------
    config : mapping
        The parsed YAML (schema ``data_schemas/configs/pipeline.json``).
    base_dir : path-like
        Relative paths in the config are relative to this folder (the config file's).
    source : str
        Named in error messages (the config file).

    Returns
    -------
    dict
        A new config with every stage section's defaults filled in.

    Raises
    ------
    UserError
        Unknown keys (naming the key and the allowed ones), wrong types, or stage sections
        that contradict each other (e.g. ``capture`` with both ``file`` and ``render``).
    """
    from data_schemas import SchemaError, validate_config

    try:
        validate_config("pipeline", dict(config), source)
    except SchemaError as exc:
        raise UserError(str(exc)) from None
    base = Path(base_dir).resolve()
    cfg = copy.deepcopy(dict(config))
    for name in STAGE_ORDER:
        if name in cfg:
            cfg[name] = {**DEFAULTS[name], **(cfg[name] or {})}
    syn = cfg.get("synthesize")
    if syn is not None and (base / syn["scene"]).is_file():
        syn["scene"] = _abs(syn["scene"], base)  # a scene file next to the config
    if syn is not None and syn["model"] == "traced" and not all(k in syn for k in ("rays", "sampler", "seed")):
        from sim.scene import load_scene

        try:
            trace = load_scene(syn["scene"]).trace
        except UserError as exc:
            raise UserError(f"{source}: synthesize.scene: {exc}") from None
        syn.update({k: v for k, v in (("rays", trace.rays), ("sampler", trace.sampler), ("seed", trace.seed))
                    if k not in syn})
    for key in ("cache", "out"):
        if key in cfg:
            cfg[key] = _abs(cfg[key], base)
    cal = cfg.get("calibrate")
    if cal is not None:
        if ("capture" in cal) == ("render" in cal):
            raise UserError(f"{source}: calibrate: give exactly one of 'capture' (a sphere capture.h5) and "
                            f"'render' (render one from the synthesized illumination)")
        if "capture" in cal:
            cal["capture"] = _abs(cal["capture"], base)
        else:
            cal["render"] = {**DEFAULTS["calibrate.render"], "mode": _capture_mode(cfg, base), **cal["render"]}
    cap = cfg.get("capture")
    if cap is not None:
        sources = [k for k in ("file", "render", "emulate", "port") if cap.get(k)]
        if len(sources) != 1:
            raise UserError(f"{source}: capture: give exactly one of 'file', 'render: true', 'emulate: true' and "
                            f"'port', got {sources or 'none'}")
        if "file" in cap:
            cap["file"] = _abs(cap["file"], base)
        cam = cap.get("camera")
        if isinstance(cam, str) and not cam.isdigit() and (base / cam).exists():
            cap["camera"] = _abs(cam, base)  # a video file next to the config
        elif cap.get("virtual_camera") and not cap.get("emulate"):
            raise UserError(f"{source}: capture: 'virtual_camera' images the emulated ring; it needs 'emulate: true'")
        elif (cap.get("emulate") or cap.get("port")) and not cap.get("virtual_camera") and "camera" not in cap:
            raise UserError(f"{source}: capture: a ring capture needs 'camera' (OpenCV index, device or video file) "
                            f"or 'virtual_camera: true'")
    nrm = cfg.get("normals")
    if nrm is not None and "lights" not in nrm:
        nrm["lights"] = "calibration" if "calibrate" in cfg else "illumination"
    return cfg


# ---------------------------------------------------------------------------------------------
# Illumination records (stage 2)

def illumination_record(model):
    """An :class:`~sim.illumination_model.IlluminationModel` as an ``illumination`` record.

    Parameters
    ----------
    model : IlluminationModel
        ``V (L, H, W, 3)``, ``led_positions (L, 3)``, ``mm_per_px``, ``gel_z``.

    Returns
    -------
    Record
        Schema ``illumination``: ``V``, ``led_positions`` (and ``V_depth``/``depth_heights``
        when the model has them); attributes ``mm_per_px``, ``gel_z`` and the model's scalar
        ``meta`` entries.

    Examples
    --------
    >>> from sim.render import bare_ring_illumination
    >>> rec = illumination_record(bare_ring_illumination((4, 6), 1.0))
    >>> rec.data["V"].shape, rec.meta["source"]
    ((24, 4, 6, 3), 'bare_ring')
    """
    from pipeline.store import Record

    data = {"V": np.asarray(model.V, dtype=np.float32), "led_positions": np.asarray(model.led_positions, np.float32)}
    if model.V_depth is not None:
        data["V_depth"] = np.asarray(model.V_depth, dtype=np.float32)
        data["depth_heights"] = np.asarray(model.depth_heights, dtype=np.float32)
    meta = {k: v for k, v in model.meta.items() if isinstance(v, (str, int, float, bool))}
    meta.update({"mm_per_px": float(model.mm_per_px), "gel_z": float(model.gel_z)})
    return Record("illumination", data, meta)


def illumination_model(rec):
    """The :class:`~sim.illumination_model.IlluminationModel` of an ``illumination`` record.

    The ray tracer's reader, :func:`sim.synthesize.model_from_record`.

    Examples
    --------
    >>> from sim.render import bare_ring_illumination
    >>> m = illumination_model(illumination_record(bare_ring_illumination((4, 6), 1.0)))
    >>> m.shape, m.num_leds
    ((4, 6), 24)
    """
    from sim.synthesize import model_from_record

    return model_from_record(rec)


def _synthesize(p: Mapping[str, Any], device: str):
    shape = (int(p["height"]), int(p["width"]))
    if p["model"] == "bare_ring":
        from sim.render import bare_ring_illumination

        return illumination_record(bare_ring_illumination(shape, float(p["mm_per_px"]), float(p["gel_z"])))
    from sim.synthesize import synthesize_record

    return synthesize_record(p["scene"], shape, float(p["mm_per_px"]), rays=int(p["rays"]), sampler=p["sampler"],
                             seed=int(p["seed"]), method=p["method"], device=device)


def _synthesize_params(p: Mapping[str, Any]) -> dict:
    keep = ["model", "height", "width", "mm_per_px"]
    keep += ["gel_z"] if p["model"] == "bare_ring" else ["rays", "sampler", "method", "seed"]
    out = {k: p[k] for k in keep}
    if p["model"] == "traced":
        # The scene's content, not its name or path, decides the result.
        from sim.scene import load_scene, scene_to_dict

        try:
            scene = scene_to_dict(load_scene(p["scene"]))
        except UserError as exc:
            raise UserError(f"synthesize: scene: {exc}") from None
        scene.pop("description", None)  # words do not change the light
        out["scene"] = scene
    return out


# ---------------------------------------------------------------------------------------------
# Virtual contacts and captures (stages 1 and 3)

def contact_surfaces(shape: tuple[int, int], mm_per_px: float, *, object: str = "sphere", size_mm: float = 3.0,
                     depth_mm: float = 0.5, contacts: int = 2, spread_mm: float = 3.0, seed: int = 0) -> list:
    """K virtual presses of one object at seeded random positions (reconstruction frame, mm).

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
    object : {"sphere", "cylinder", "cone", "flat_punch"}
        ``size_mm`` is the radius (the cone's half angle in degrees).
    depth_mm : float
        Indentation depth.
    contacts : int
        K.
    spread_mm : float
        Centres are uniform in a disc of this radius, clipped so the contact stays inside
        the image.
    seed : int

    Returns
    -------
    list of HeightField
        K surfaces of shape (H, W).

    Examples
    --------
    >>> fs = contact_surfaces((20, 30), 0.2, contacts=3, size_mm=1.0, depth_mm=0.3, seed=1)
    >>> len(fs), fs[0].shape, round(float(fs[0].height.max()), 1)
    (3, (20, 30), 0.3)
    """
    from sim import geometry as G

    makers: dict[str, Callable] = {"sphere": G.sphere, "cylinder": G.cylinder, "flat_punch": G.flat_punch,
                                   "cone": G.cone}
    if object not in makers:
        raise UserError(f"capture: object must be one of {', '.join(makers)}, got {object!r}")
    h, w = shape
    rng = np.random.default_rng(seed)
    # Keep the whole contact inside the image where the image is large enough.
    reach = 0.0 if object == "cone" else float(size_mm)
    lim = np.maximum(np.array([w, h]) * mm_per_px / 2 - reach, 0.0)
    out = []
    for _ in range(int(contacts)):
        r, a = spread_mm * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        c = np.clip([r * np.cos(a), r * np.sin(a)], -lim, lim)
        out.append(makers[object](shape, mm_per_px, float(size_mm), float(depth_mm), center=(float(c[0]), float(c[1]))))
    return out


def _render_capture(model, mode: str, surfaces, noise_dn: float, target_dn: float, seed: int, device: str):
    from sim.rendered_capture import render_capture

    try:
        return render_capture(model, mode, surfaces, noise_dn=float(noise_dn), target_dn=float(target_dn),
                              seed=int(seed), device=device)
    except ValueError as exc:
        raise UserError(f"capture: {exc}") from None


def virtual_sensor_capture(model, mode: str, surfaces, *, faults: str | None = None, fps: float = 100.0,
                           frames_per_pattern: int = 1, noise_dn: float = 1.0, target_dn: float = 200.0,
                           seed: int = 0, device: str = "cpu", progress: bool = True):
    """Capture through the ring emulator (on a pty) and the rendering virtual camera.

    The real capture plan (:func:`pipeline.capture.plan.run_capture`) drives the emulated
    ring over its serial protocol; the camera is :class:`sim.virtual_camera.VirtualCamera`
    rendering the gel under the LED state the emulator shows, with the plan choosing which
    of ``surfaces`` is pressed for each contact instance.

    Parameters
    ----------
    model : IlluminationModel
    mode : str
        Lighting mode name or file.
    surfaces : list of HeightField, length K
    faults : str, optional
        The emulator's fault spec (``pipeline.capture.emulator.parse_faults``).
    fps, frames_per_pattern, noise_dn, target_dn, seed, device
        Camera clock, frames averaged, read noise, exposure target, noise seed, torch device.

    Returns
    -------
    Record
        Schema ``capture`` with ``truth/height (K, H, W)``, ``truth/normals (K, H, W, 3)``,
        ``truth/albedo (H, W, 3)``, and the exposure ``mu`` the frames were rendered with.
    """
    try:
        from pipeline.capture.virtual import VirtualSensorSpec  # type: ignore[import-not-found]
    except ModuleNotFoundError as exc:
        if exc.name != "pipeline.capture.virtual":
            raise
    else:
        # The capture package's own virtual sensor (iristac capture --virtual-camera).
        from pipeline.capture.session import capture

        spec = VirtualSensorSpec(illumination=model, contacts=list(surfaces), noise_dn=float(noise_dn),
                                 target_dn=float(target_dn), fps=float(fps), seed=int(seed), device=device)
        with tempfile.TemporaryDirectory(prefix="iristac-capture-") as tmp:
            res = capture(Path(tmp) / "capture.h5", mode=mode, emulate=True, faults=faults, virtual_camera=spec,
                          frames_per_pattern=int(frames_per_pattern), seed=int(seed), progress=progress)
        return res.record
    return _plan_driven_capture(model, mode, surfaces, faults=faults, fps=fps, frames_per_pattern=frames_per_pattern,
                                noise_dn=noise_dn, target_dn=target_dn, seed=seed, device=device, progress=progress)


def _plan_driven_capture(model, mode, surfaces, *, faults, fps, frames_per_pattern, noise_dn, target_dn, seed, device,
                         progress):
    # Until pipeline.capture.virtual is on main: the plan drives sim.virtual_camera directly.
    from pipeline.capture.client import RingClient
    from pipeline.capture.emulator import RingEmulator, parse_faults
    from pipeline.capture.plan import CaptureSettings, run_capture
    from pipeline.capture.session import load_patterns
    from pipeline.store import Record
    from sim.render import RenderSettings, auto_exposure
    from sim.virtual_camera import VirtualCamera, ring_led_state

    patterns = load_patterns(mode)
    if patterns.led_count != model.num_leds:
        raise UserError(f"capture: mode {mode!r} drives {patterns.led_count} LEDs, the illumination has "
                        f"{model.num_leds}")
    mu = auto_exposure(model, patterns.drive, patterns.brightness, target_dn=float(target_dn))
    settings = RenderSettings(exposure=mu, read_noise=float(noise_dn), saturation=True, bit_depth=8, seed=int(seed))

    class _PlanDrivenCamera(VirtualCamera):
        # The plan (on_contact), not the clock, decides which surface is pressed.
        current = -1

        def contact_at(self, t: float) -> int:
            return self.current

        def read(self, timeout: float | None = 5.0):
            # The capture plan reads the exposure window from info["exposure"] (the
            # renderer's exposure mu is recorded in the capture's attributes instead).
            frame = super().read(timeout)
            frame.info["exposure"] = frame.info["exposure_window"]
            return frame

    settings_c = CaptureSettings(frames_per_pattern=int(frames_per_pattern), contacts=len(surfaces),
                                 mm_per_px=float(model.mm_per_px))
    with RingEmulator(led_count=patterns.led_count, faults=parse_faults(faults), seed=int(seed)) as emu, \
            tempfile.TemporaryDirectory(prefix="iristac-capture-") as tmp:
        cam = _PlanDrivenCamera(model, ring_led_state(emu), [(0.0, s) for s in surfaces], settings=settings,
                                fps=float(fps), device=device)

        def press(k: int) -> None:
            cam.current = k

        with RingClient(emu.path) as ring:
            cam.open()
            try:
                res = run_capture(patterns, ring, cam, Path(tmp) / "capture.h5", settings_c, truth=emu,
                                  on_contact=press, source="virtual",
                                  device_info={"emulated_ring": True, "faults": faults or ""}, progress=progress)
            finally:
                cam.close()
    rec = res.record
    data = dict(rec.data)
    h, w = model.shape
    data["truth/height"] = np.stack([s.height for s in surfaces]).astype(np.float32)
    data["truth/normals"] = np.stack([s.normals for s in surfaces]).astype(np.float32)
    data["truth/albedo"] = np.ones((h, w, 3), np.float32)
    meta = {**rec.meta, "exposure": float(mu), "mislabeled": res.mislabeled, "render_settings": settings.to_dict()}
    return Record("capture", data, meta)


def _capture(p: Mapping[str, Any], inputs: Mapping[str, Any], device: str, progress: bool):
    from pipeline.store import read_record

    if p.get("file"):
        return read_record(p["file"], schema="capture")
    if p.get("render") or p.get("virtual_camera"):
        model = illumination_model(inputs["synthesize"])
        surfaces = contact_surfaces(model.shape, model.mm_per_px, object=p["object"], size_mm=p["size_mm"],
                                    depth_mm=p["depth_mm"], contacts=p["contacts"], spread_mm=p["spread_mm"],
                                    seed=p["seed"])
        if p.get("render"):
            return _render_capture(model, p["mode"], surfaces, p["noise_dn"], p["target_dn"], p["seed"], device)
        return virtual_sensor_capture(model, p["mode"], surfaces, faults=p.get("faults"), fps=p["fps"],
                                      frames_per_pattern=p["frames_per_pattern"], noise_dn=p["noise_dn"],
                                      target_dn=p["target_dn"], seed=p["seed"], device=device, progress=progress)
    # A real camera (with the real ring, or the emulated one): the operator presses.
    from pipeline.capture.session import capture, prompt_contact

    with tempfile.TemporaryDirectory(prefix="iristac-capture-") as tmp:
        res = capture(Path(tmp) / "capture.h5", mode=p["mode"], port=p.get("port"), emulate=bool(p.get("emulate")),
                      faults=p.get("faults"), camera=p["camera"], frames_per_pattern=int(p["frames_per_pattern"]),
                      contacts=int(p["contacts"]), mm_per_px=float(p["mm_per_px"]), seed=int(p["seed"]),
                      on_contact=prompt_contact, progress=progress)
    return res.record


def _capture_params(p: Mapping[str, Any]) -> dict:
    if p.get("file"):
        return {"source": "file"}  # the file's content hash is an input of the stage
    common = ["mode", "contacts", "seed", "frames_per_pattern"]
    if p.get("render"):
        keys = ["mode", "object", "size_mm", "depth_mm", "contacts", "spread_mm", "noise_dn", "target_dn", "seed"]
        return {"source": "render", **{k: p[k] for k in keys}}
    if p.get("virtual_camera"):
        keys = common + ["object", "size_mm", "depth_mm", "spread_mm", "noise_dn", "target_dn", "fps", "faults"]
        return {"source": "emulator", **{k: p.get(k) for k in keys}}
    keys = common + ["port", "emulate", "faults", "camera", "mm_per_px"]
    return {"source": "hardware", **{k: p.get(k) for k in keys}}


def _calibrate(p: Mapping[str, Any], inputs: Mapping[str, Any], device: str):
    from calibration.calibrate import calibrate
    from pipeline.store import read_record

    with tempfile.TemporaryDirectory(prefix="iristac-calibrate-") as tmp:
        if "render" in p:
            from sim.rendered_capture import write_capture

            r = p["render"]
            model = illumination_model(inputs["synthesize"])
            presses = contact_surfaces(model.shape, model.mm_per_px, object="sphere", size_mm=p["ball_radius_mm"],
                                       depth_mm=r["depth_mm"], contacts=r["presses"], spread_mm=r["spread_mm"],
                                       seed=r["seed"])
            src = write_capture(Path(tmp) / "sphere_capture.h5",
                                _render_capture(model, r["mode"], presses, r["noise_dn"], r["target_dn"], r["seed"],
                                                device))
        else:
            src = p["capture"]
        try:
            res = calibrate(src, float(p["ball_radius_mm"]), p.get("mm_per_px"), p["model"], folds=int(p["folds"]))
        except UserError as exc:
            if "render" not in p:
                raise
            # The rendered file is temporary: name the config fields that made it instead.
            msg = str(exc).replace(str(src), "the sphere capture rendered from calibrate.render")
            raise UserError(f"{msg} (check calibrate.render: presses, depth_mm, spread_mm, and "
                            f"calibrate.ball_radius_mm)") from None
        return read_record(res.save(Path(tmp) / "calibration.h5"), schema="calibration")


def _calibrate_params(p: Mapping[str, Any]) -> dict:
    out = {k: p.get(k) for k in ("ball_radius_mm", "mm_per_px", "model", "folds")}
    out["source"] = "render" if "render" in p else "file"
    if "render" in p:
        out["render"] = dict(p["render"])
    return out


def _normals(p: Mapping[str, Any], inputs: Mapping[str, Any], device: str):
    from pipeline.reconstruct import load_lights, normals_record

    cal = inputs.get("calibrate") if p["lights"] == "calibration" else None
    ill = inputs.get("synthesize") if p["lights"] == "illumination" else None
    lights = load_lights(inputs["capture"], cal, ill)
    return normals_record(inputs["capture"], lights, solver=p["solver"], ratio=bool(p["ratio"]),
                          max_condition=float(p["max_condition"]), device=device, dtype=p["dtype"])


def _depth(p: Mapping[str, Any], inputs: Mapping[str, Any]):
    from pipeline.reconstruct import depth_record

    return depth_record(inputs["normals"], p["integrator"])


# ---------------------------------------------------------------------------------------------
# The graph

def _file_key(path: str, field: str) -> str:
    try:
        return file_input_key(path)
    except UserError as exc:
        raise UserError(f"config {field}: {exc}") from None


def build_stages(config: Mapping[str, Any], *, device: str | None = None, progress: bool = False) -> list[Stage]:
    """The stages of a resolved config (:func:`resolve_config`), in run order.

    Parameters
    ----------
    config : mapping
        A config returned by :func:`resolve_config`.
    device : str, optional
        Torch device (default: the config's ``device``, else ``cpu``). Not part of any key.
    progress : bool
        Progress bars inside long stages (capture).

    Returns
    -------
    list of Stage

    Raises
    ------
    UserError
        A stage needs one that is not configured (e.g. ``capture.render`` without
        ``synthesize``, ``normals.lights: calibration`` without ``calibrate``).
    """
    from pipeline.reconstruct import DEPTH_VERSION, NORMALS_VERSION

    dev = device or config.get("device") or "cpu"
    stages: list[Stage] = []
    present = set(config) & set(STAGE_ORDER)

    def need(stage: str, other: str, why: str) -> None:
        if other not in present:
            what = f"stage {stage!r} {why}".rstrip()
            raise UserError(f"config: {what} needs the {other!r} section, which is absent")

    if "synthesize" in config:
        p = config["synthesize"]
        version = 1
        if p["model"] == "traced":
            from sim.synthesize import STAGE_VERSION as version
        stages.append(Stage("synthesize", int(version), _synthesize_params(p), [],
                            lambda inputs, p=p: _synthesize(p, dev)))
    if "calibrate" in config:
        p = config["calibrate"]
        if "render" in p:
            need("calibrate", "synthesize", "with 'render'")
            deps, extra = ["synthesize"], []
        else:
            deps, extra = [], [_file_key(p["capture"], "calibrate.capture")]
        stages.append(Stage("calibrate", _VERSIONS["calibrate"], _calibrate_params(p), deps,
                            lambda inputs, p=p: _calibrate(p, inputs, dev), extra))
    if "capture" in config:
        p = config["capture"]
        if p.get("file"):
            deps, extra = [], [_file_key(p["file"], "capture.file")]
        elif p.get("render") or p.get("virtual_camera"):
            need("capture", "synthesize", "with a virtual sensor")
            deps, extra = ["synthesize"], []
        else:
            deps, extra = [], []
        stages.append(Stage("capture", _VERSIONS["capture"], _capture_params(p), deps,
                            lambda inputs, p=p: _capture(p, inputs, dev, progress), extra))
    if "normals" in config:
        p = config["normals"]
        need("normals", "capture", "")
        light_stage = "calibrate" if p["lights"] == "calibration" else "synthesize"
        need("normals", light_stage, f"with lights: {p['lights']}")
        params = {k: p[k] for k in ("solver", "ratio", "max_condition", "dtype", "lights")}
        stages.append(Stage("normals", NORMALS_VERSION, params, ["capture", light_stage],
                            lambda inputs, p=p: _normals(p, inputs, dev)))
    if "depth" in config:
        p = config["depth"]
        need("depth", "normals", "")
        stages.append(Stage("depth", DEPTH_VERSION, {"integrator": p["integrator"]}, ["normals"],
                            lambda inputs, p=p: _depth(p, inputs)))
    return stages
