"""Stage 3, capture: frames of contact instances under every pattern of a lighting mode.

Four sources (a run config's ``capture`` section names exactly one):

``file``
    An existing ``capture.h5``. Its content hash is the stage's input, so a moved or renamed
    file is still cached; :func:`capture_key` gives a standalone capture file the same
    identity when ``iristac reconstruct`` or ``batch`` reads it.
``render``
    Frames rendered directly (:func:`sim.rendered_capture.render_capture`) from the
    synthesized illumination: no ring, no camera clock.
``emulate`` + ``virtual_camera``
    The ring emulator on a pseudo-terminal driven over the real protocol by the capture plan,
    and the rendering virtual camera (:func:`virtual_sensor_capture`).
``port`` / ``emulate`` + ``camera``
    Hardware (:func:`pipeline.capture.session.capture`): the operator presses each contact.

Virtual captures press the contact object named ``object``
(:func:`sim.contacts.contact_surfaces`). The parameters that change the result, and
so enter the key, are per source (:func:`params`). The demo and ``compare-modes`` capture
through :func:`run`, ``iristac run`` through :func:`node`.
"""

from __future__ import annotations

import tempfile
from pathlib import Path
from typing import Any, Mapping

from pipeline.base.errors import UserError
from pipeline.base.identity import file_input_key, is_entry, record_key
from pipeline.stages.base import StageSpec, config_path

__all__ = ["SPEC", "params", "compute", "run", "node", "resolve", "scale", "capture_key", "virtual_sensor_capture"]

SPEC = StageSpec("capture", version=1, schema="capture",
                 defaults={"mode": "monochromatic", "object": "sphere", "size_mm": 3.0, "depth_mm": 0.5,
                           "contacts": 2, "spread_mm": 3.0, "noise_dn": 1.0, "target_dn": 200.0, "seed": 0,
                           "fps": 100.0, "frames_per_pattern": 1, "mm_per_px": 0.1})


def source_of(p: Mapping[str, Any]) -> str:
    """``file``, ``render``, ``emulator`` (emulated ring + virtual camera) or ``hardware``."""
    if p.get("file"):
        return "file"
    if p.get("render"):
        return "render"
    if p.get("virtual_camera"):
        return "emulator"
    return "hardware"


def params(p: Mapping[str, Any]) -> dict:
    """The key parameters of a (default-filled) capture section.

    Examples
    --------
    >>> params({"file": "c.h5"})
    {'source': 'file'}
    """
    source = source_of(p)
    if source == "file":
        return {"source": "file"}  # the file's content hash is an input of the stage
    common = ["mode", "contacts", "seed", "frames_per_pattern"]
    if source == "render":
        keys = ["mode", "object", "size_mm", "depth_mm", "contacts", "spread_mm", "noise_dn", "target_dn", "seed"]
        return {"source": "render", **{k: p[k] for k in keys}}
    if source == "emulator":
        keys = common + ["object", "size_mm", "depth_mm", "spread_mm", "noise_dn", "target_dn", "fps", "faults"]
        return {"source": "emulator", **{k: p.get(k) for k in keys}}
    keys = common + ["port", "emulate", "faults", "camera", "mm_per_px"]
    return {"source": "hardware", **{k: p.get(k) for k in keys}}


def capture_key(store, rec) -> str:
    """The identity of a capture record as an input: its stage key when it is a store entry,
    else this stage's key over a file (what ``capture: {file: ...}`` in a run config keys),
    else the digest of its content. A video read as a capture
    (:func:`pipeline.capture.video_frames.video_capture`) is keyed on its content, its reference
    choice and its pixel pitch."""
    if not is_entry(rec) and rec.path is not None:
        p = params({"file": str(rec.path)})
        if rec.meta.get("source") == "video":
            p = {**p, "video_reference": str(rec.meta["video_reference"]), "mm_per_px": float(rec.meta["mm_per_px"])}
        return SPEC.key(store, p, [file_input_key(rec.path)]).digest
    return record_key(rec)


def _object_names() -> tuple[str, ...]:
    from sim.contacts import OBJECTS

    return OBJECTS


def _surfaces(model, p: Mapping[str, Any]) -> list:
    from sim.contacts import contact_surfaces

    return contact_surfaces(p["object"], model.shape, model.mm_per_px, p["contacts"], size_mm=p.get("size_mm"),
                            depth_mm=p.get("depth_mm", 0.5), spread_mm=p.get("spread_mm", 3.0), seed=p["seed"])


def render(model, mode, surfaces, noise_dn: float, target_dn: float, seed: int, device: str = "cpu"):
    """Frames rendered directly (no ring, no camera clock): a ``capture`` record with truth."""
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
    ring over its serial protocol; the camera is :class:`pipeline.capture.virtual.ContactCamera`
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
        Camera clock, frames averaged, read noise, exposure target, seed (of the camera noise
        and of the emulator's faults), torch device.

    Returns
    -------
    Record
        Schema ``capture`` with ``truth/height (K, H, W)``, ``truth/normals (K, H, W, 3)``,
        ``truth/albedo (H, W, 3)``, and the exposure ``mu`` the frames were rendered with.
    """
    from pipeline.capture.session import capture
    from pipeline.capture.virtual import VirtualSensorSpec

    spec = VirtualSensorSpec(illumination=model, contacts=list(surfaces), noise_dn=float(noise_dn),
                             target_dn=float(target_dn), fps=float(fps), seed=int(seed), device=device)
    with tempfile.TemporaryDirectory(prefix="iristac-capture-") as tmp:
        res = capture(Path(tmp) / "capture.h5", mode=mode, emulate=True, faults=faults, virtual_camera=spec,
                      frames_per_pattern=int(frames_per_pattern), seed=int(seed), progress=progress)
    if res.mislabeled:
        raise UserError(f"capture: {res.mislabeled} frames were stored under the wrong pattern")
    return res.record


def compute(p: Mapping[str, Any], model=None, *, device: str = "cpu", progress: bool = False):
    """The ``capture`` record of a (default-filled) capture section (no caching).

    ``model`` is the :class:`~sim.illumination_model.IlluminationModel` a virtual capture
    renders with.
    """
    from pipeline.base.store import read_record

    source = source_of(p)
    if source == "file":
        return read_record(p["file"], schema="capture")
    if source in ("render", "emulator"):
        surfaces = _surfaces(model, p)
        if source == "render":
            return render(model, p["mode"], surfaces, p["noise_dn"], p["target_dn"], p["seed"], device)
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


def run(store, section: Mapping[str, Any], model=None, model_key=None, *, device: str = "cpu",
        progress: bool = False, force: bool = False, heal: bool = True):
    """``(record, key, cached)`` of a capture section (defaults filled in here) through ``store``.

    ``model`` and ``model_key`` are the illumination model a virtual capture renders with and
    its identity (the synthesize stage's key).
    """
    p = {**SPEC.defaults, **section}
    source = source_of(p)
    if source == "file":
        inputs = [file_input_key(p["file"])]
    elif source in ("render", "emulator"):
        if model is None or model_key is None:
            raise UserError("capture: a virtual capture needs the illumination model and its key")
        inputs = [model_key]
        if p["object"] not in _object_names() and Path(p["object"]).is_file():
            inputs.append(file_input_key(p["object"]))  # a height-map file: its content, not its name
    else:
        inputs = []
    return SPEC.get_or_compute(store, params(p), inputs,
                               lambda: compute(p, model, device=device, progress=progress), force=force, heal=heal)


def mode_of(cfg: Mapping[str, Any], base: Path = Path(".")) -> str:
    """The lighting mode of a run config's capture (a capture file's own ``mode`` attribute; a
    relative path is relative to ``base``, the config's folder)."""
    cap = cfg.get("capture") or {}
    if cap.get("file"):
        from pipeline.base.store import StoreError, read_record

        try:
            mode = read_record(config_path(cap["file"], base), schema="capture", load=False).meta.get("mode")
        except StoreError:
            mode = None  # the capture stage reports the bad file when it runs
        if mode:
            return str(mode)
    return cap.get("mode", SPEC.defaults["mode"])


def scale(cfg: Mapping[str, Any]) -> float | None:
    """The ``mm_per_px`` a run config's capture will record (None: its file is unreadable).

    A capture file's own attribute; a virtual capture's is the synthesized grid's; hardware's
    the section's ``mm_per_px``.
    """
    cap = cfg.get("capture") or {}
    source = source_of(cap)
    if source == "file":
        from pipeline.base.store import StoreError, read_record

        try:
            return float(read_record(cap["file"], schema="capture", load=False).meta["mm_per_px"])
        except (StoreError, KeyError):
            return None  # the capture stage reports the bad file when it runs
    if source in ("render", "emulator"):
        return float(cfg["synthesize"]["mm_per_px"])
    return float(cap["mm_per_px"])


def resolve(cap: dict, config: Mapping[str, Any], base: Path, source: str) -> None:
    """Check a run config's ``capture`` section and make its paths absolute, in place."""
    sources = [k for k in ("file", "render", "emulate", "port") if cap.get(k)]
    if len(sources) != 1:
        raise UserError(f"{source}: capture: give exactly one of 'file', 'render: true', 'emulate: true' and "
                        f"'port', got {sources or 'none'}")
    if "file" in cap:
        cap["file"] = config_path(cap["file"], base)
    cam = cap.get("camera")
    if isinstance(cam, str) and not cam.isdigit() and (base / cam).exists():
        cap["camera"] = config_path(cam, base)  # a video file next to the config
    elif cap.get("virtual_camera") and not cap.get("emulate"):
        raise UserError(f"{source}: capture: 'virtual_camera' images the emulated ring; it needs 'emulate: true'")
    elif (cap.get("emulate") or cap.get("port")) and not cap.get("virtual_camera") and "camera" not in cap:
        raise UserError(f"{source}: capture: a ring capture needs 'camera' (OpenCV index, device or video file) "
                        f"or 'virtual_camera: true'")


def node(config: Mapping[str, Any], ctx):
    """The graph node of a resolved run config's ``capture`` section."""
    from pipeline.stages.graph import Stage
    from pipeline.stages.synthesize import illumination_model

    p = config["capture"]
    source = source_of(p)
    if source == "file":
        try:
            deps, extra = [], [file_input_key(p["file"])]
        except UserError as exc:
            raise UserError(f"config capture.file: {exc}") from None
    elif source in ("render", "emulator"):
        ctx.need("capture", "synthesize", "with a virtual sensor")
        deps, extra = ["synthesize"], []
    else:
        deps, extra = [], []

    def compute_node(inputs):
        model = illumination_model(inputs["synthesize"]) if "synthesize" in inputs else None
        return compute(p, model, device=ctx.device, progress=ctx.progress)

    return Stage(SPEC.name, SPEC.version, params(p), deps, compute_node, extra, schema=SPEC.schema)
