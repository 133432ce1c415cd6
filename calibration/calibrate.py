"""The calibration stage: sphere-indentation capture -> circles, light models, validation.

:func:`calibrate` detects each press's contact circle, builds sphere-cap truth, checks that
the patterns give three independent light directions, fits every requested model on all
accepted presses, cross-validates each by leaving presses out, and returns a
:class:`CalibrationResult` that :meth:`CalibrationResult.save` writes as ``calibration.h5``.
"""

from __future__ import annotations

import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from calibration.ball_gain import OutOfFoldBalls
from calibration.detect import Circle, DetectOptions, detect_contacts, drift_settings
from calibration.gate import CalibrationRefused, GateSettings, Verdict, judge, model_problems, shading_explained
from calibration.labels import capture_label_circles, has_labels, label_errors
from calibration.models import (
    MODEL_NAMES,
    NEIGHBOURHOOD_MODELS,
    CalibrationModel,
    FarFieldModel,
    LightFieldModel,
    LUTModel,
    MLPModel,
    NearFieldModel,
    TracedModel,
    check_light_rank,
)
from calibration.models.base import fit_tilt_gain, scale_tilt
from calibration.models.conv import CONV_MODELS, ball_downsample
from calibration.models.led_geometry import geometry_basis
from calibration.refine import refine_centres
from calibration.samples import Samples, collect_samples
from calibration.shading_fit import refit_by_shading
from calibration.validate import INVALID_ERROR_DEG, cross_validate, cv_report
from pipeline.base.capture import Capture, read_capture
from pipeline.base.errors import UserError
from pipeline.results.evaluate import angular_error_deg
from sim.illumination_model import IlluminationModel

__all__ = ["CalibrationResult", "CircleFit", "calibrate", "find_circles", "label_errors", "read_illumination", "CIRCLE_COLUMNS",
           "CIRCLE_SOURCES"]

#: Columns of the ``circles (K, 8)`` dataset of calibration.h5.
CIRCLE_COLUMNS = ("center_x", "center_y", "radius_px", "contact_radius_px", "quality", "accepted", "snr",
                  "residual_px", "shift_x", "shift_y")


#: What ``calibrate(..., circles=...)`` accepts besides a list of circles: where the contact circles come from.
CIRCLE_SOURCES = ("auto", "detected", "labels")

#: Said with every calibration report (``summary()["cv_note"]``): CV figures are not what new presses see.
CV_NOTE = ("CV is optimistic (the held-out presses shaped the circles and the choice of model); for the error on "
           "presses the calibration never saw, import a separate test capture of the same sensor and run "
           "iristac eval calibration CAL.h5 TEST_CAPTURE.h5")


@dataclass
class CalibrationResult:
    """Everything :func:`calibrate` found.

    Attributes
    ----------
    circles : list of Circle
    models : dict
        name -> fitted model (on all accepted presses).
    reports : dict
        name -> ``{"fit": ..., "cv": ..., "seconds": ...}`` or ``{"skipped": reason}``.
    labels : dict or None
        Comparison with hand labels (``center_error_px_median``, ``radius_error_px_median``, ...).
    ball_radius_mm, mm_per_px : float
    shape : (H, W)
    num_patterns, num_channels : int
    light_rank_ratio : float
    markers : ndarray, shape (H, W), bool, or None
        Printed gel markers the calibration filled in and left out (saved as ``markers``).
    verdict : Verdict or None
        The quality gate's (:mod:`calibration.gate`); :meth:`save` refuses a failed one
        unless forced.
    """

    circles: list[Circle]
    models: dict[str, CalibrationModel]
    reports: dict[str, dict[str, Any]]
    labels: dict[str, Any] | None
    ball_radius_mm: float
    mm_per_px: float
    shape: tuple[int, int]
    num_patterns: int
    num_channels: int
    light_rank_ratio: float
    meta: dict[str, Any] = field(default_factory=dict)
    markers: np.ndarray | None = None
    verdict: Verdict | None = None

    @property
    def best_model(self) -> str | None:
        """The fitted model with the lowest cross-validated mean angular error among the usable ones
        (:func:`calibration.gate.model_problems`; among all when none is usable)."""
        return _best(self.reports)

    @property
    def circles_used(self) -> str:
        """What the models were fitted to, in words (``summary()["circles_used"]``)."""
        cs = self.meta.get("circle_settings", {})
        source = cs.get("circles", "detected")
        if source == "labels":
            return "hand labels (labels/center_xy, labels/radius_px; contact radius at most 0.95 x the ball's)"
        if source == "given":
            return "circles given by the caller"
        if cs.get("refine_iterations") and cs.get("refine_model"):
            return (f"detected (edge detector, centres refined by the {cs['refine_model']} model, "
                    f"{cs['refine_iterations']} passes)")
        return "detected (edge detector)"

    @property
    def best_light_field_model(self) -> str | None:
        """The best-validated model that exports a light field (far, near, traced), usable ones first."""
        return _best({k: r for k, r in self.reports.items() if isinstance(self.models.get(k), LightFieldModel)})

    def summary(self) -> dict[str, Any]:
        """The stable JSON summary printed by ``iristac calibrate --json``."""
        out: dict[str, Any] = {
            "presses": len(self.circles),
            "accepted": int(sum(c.accepted for c in self.circles)),
            "models": {},
            "best_model": self.best_model,
            "circles": [c.to_dict() for c in self.circles],
            "circles_used": self.circles_used,
        }
        for name, rep in self.reports.items():
            if "skipped" in rep:
                out["models"][name] = {"skipped": rep["skipped"], "cv_mean_angular_error_deg": None,
                                       "cv_median_angular_error_deg": None, "seconds": 0.0}
                continue
            cv = rep["cv"]
            none_valid = cv["invalid_fraction"] >= 1.0
            out["models"][name] = {
                # Internally an invalid prediction scores 90 deg (a model cannot win by refusing
                # to answer); when *no* prediction is valid that number means nothing: None.
                "cv_mean_angular_error_deg": None if none_valid else cv["cv_mean_angular_error_deg"],
                "cv_median_angular_error_deg": None if none_valid else cv["cv_median_angular_error_deg"],
                "cv_invalid_fraction": cv["invalid_fraction"],
                "cv_answered_mean_angular_error_deg": cv.get("cv_answered_mean_angular_error_deg"),
                "seconds": rep["seconds"],
                "fit": rep["fit"],
                "tilt_gain": cv.get("tilt_gain", 1.0),
            }
            if none_valid:
                out["models"][name]["note"] = "no valid predictions on the held-out presses"
            # A model the gate's thresholds find useless says so (calibration.gate.model_problems).
            out["models"][name]["usable"] = not rep.get("problems")
            out["models"][name]["problems"] = list(rep.get("problems") or [])
        if self.labels is not None:
            out.update(self.labels)
        for key in ("reference", "drift", "ball_fit", "prior"):  # prior: calibration.prior's adaptation
            if key in self.meta:
                out[key] = self.meta[key]
        if self.verdict is not None:
            out["quality_gate"] = self.verdict.to_dict()
        out["cv_note"] = CV_NOTE
        return out

    def save(self, path: str | Path, *, force: bool = False) -> Path:
        """Write ``calibration.h5``: circles, every fitted model, the validation report.

        A calibration the quality gate failed (:attr:`verdict`) raises
        :class:`calibration.gate.CalibrationRefused` (nothing is written) unless ``force``;
        forced, the file's ``quality_gate`` attribute keeps the verdict.

        Layout: ``circles (K, 8)`` (columns :data:`CIRCLE_COLUMNS`); ``light_field (P, C, H, W, 3)``
        and optional ``flat_field (P, C, H, W)`` of the best light-field model (attribute
        ``light_field_model``); ``light_vectors (P, C, 3)`` of the far-field model;
        ``models/<name>/...`` every fitted model's arrays (``to_arrays``; a LUT is
        ``LookupTable.from_arrays``-ready); attributes ``chosen_model`` (best by CV),
        ``circle_reasons``, ``validation`` (per model: fit report and CV report), ``summary``.
        """
        from pipeline.base.store import Record, write_record

        if self.verdict is not None and not self.verdict.passed and not force:
            raise CalibrationRefused(self.verdict.message(str(path)), self.verdict)
        # One row per press (the stage schema's (K, *) ``circles``); columns in CIRCLE_COLUMNS.
        data: dict[str, np.ndarray] = {"circles": np.array(
            [[*c.center_xy, c.radius_px, c.contact_radius_px, c.quality, float(c.accepted), c.snr, c.residual_px,
              *c.shift_xy]
             for c in self.circles], dtype=np.float32).reshape(-1, len(CIRCLE_COLUMNS))}
        best_lf = self.best_light_field_model
        if best_lf is not None:
            data["light_field"] = self.models[best_lf].light_field(self.shape)
            flat = self.models[best_lf].flat_field()
            if flat is not None:
                data["flat_field"] = np.asarray(flat, dtype=np.float32)
        if "far" in self.models:
            data["light_vectors"] = self.models["far"].lights.astype(np.float32)
        if self.markers is not None:
            data["markers"] = np.asarray(self.markers).astype(np.uint8)
        for name, model in self.models.items():
            for k, v in {**model.to_arrays(), **model.output_arrays()}.items():
                data[f"models/{name}/{k}"] = np.asarray(v)
            if isinstance(model, LightFieldModel):
                data[f"models/{name}/light_field"] = model.light_field(self.shape)
        meta = {
            "ball_radius_mm": float(self.ball_radius_mm),
            "mm_per_px": float(self.mm_per_px),
            "models": list(self.models),
            "chosen_model": self.best_model or "",
            "light_field_model": best_lf or "",
            "circle_columns": list(CIRCLE_COLUMNS),
            "circle_reasons": [c.reason for c in self.circles],
            "validation": {k: r for k, r in self.reports.items()},
            # How the circles were found, so that a test capture's truth is found the same way.
            "circle_settings": self.meta.get("circle_settings", {}),
            "summary": {k: v for k, v in self.summary().items() if k != "circles"},
            "quality_gate": self.verdict.to_dict() if self.verdict is not None else {},
            # A calibration adapted from another unit's (calibration.prior): which, and how.
            **({"prior": self.meta["prior"]} if "prior" in self.meta else {}),
        }
        meta = json.loads(json.dumps(meta, default=float))
        return write_record(Path(path), Record(schema="calibration", data=data, meta=meta))


def _best(reports: dict[str, dict[str, Any]]) -> str | None:
    """Lowest CV among the usable models with a valid CV (``problems`` empty), else among all with one."""
    scored = {k: r["cv"]["cv_mean_angular_error_deg"] for k, r in reports.items()
              if "cv" in r and r["cv"]["invalid_fraction"] < 1.0}
    usable = {k: v for k, v in scored.items() if not reports[k].get("problems")}
    pool = usable or scored
    return min(pool, key=pool.get) if pool else None


def read_illumination(path: str | Path) -> IlluminationModel:
    """Read an ``illumination`` record (the ray tracer's ``illumination.h5``) for the traced model.

    Goes through :func:`sim.synthesize.load_illumination` (schema-validated by the stage
    store); a missing or invalid file raises :class:`UserError` naming it.
    """
    from sim.synthesize import load_illumination

    path = Path(path)
    if not path.is_file():
        raise UserError(f"{path}: no such file (expected an 'illumination' HDF5 record from iristac sim trace)")
    try:
        return load_illumination(path)
    except ValueError as exc:  # IlluminationModel's own checks (shapes, NaN)
        raise UserError(f"{path}: {exc}") from None


def model_factories(names, capture: Capture, illumination, saturation, model_options, ball_px: float | None = None
                    ) -> dict[str, Callable | str]:
    """Name -> a factory of a fresh model with the caller's options (or why the model cannot be
    fitted here). ``ball_px``: the ball's radius in pixels, which sizes the default network's
    window (:func:`calibration.models.conv.ball_downsample`) where ``downsample`` is not given."""
    out: dict[str, Callable | str] = {}
    opts = model_options or {}
    p, c = capture.frames.shape[1], capture.frames.shape[4]
    for name in names:
        o = opts.get(name, {})
        if name == "far":
            out[name] = lambda o=o: FarFieldModel(**o)
        elif name == "near":
            out[name] = lambda o=o: NearFieldModel(**o)
        elif name == "traced":
            V = getattr(illumination, "V", illumination)
            o = dict(o)
            correct = bool(o.pop("correct_geometry", False))
            if V is None:
                out[name] = "no illumination model (LED fields V) given for this sensor"
            else:
                if np.asarray(V).shape[1:3] != capture.shape:
                    raise UserError(f"calibrate: the illumination model is {np.asarray(V).shape[1:3]} pixels (H, W) "
                                    f"but the capture is {capture.shape}; trace it on the capture's pixel grid")
                if correct:
                    if not isinstance(illumination, IlluminationModel):
                        raise UserError("calibrate: LED geometry corrections need an IlluminationModel (LED "
                                        "positions, gel_z, mm_per_px), not bare fields")
                    o["basis"] = geometry_basis(illumination.led_positions, None, illumination.shape,
                                                illumination.mm_per_px, illumination.gel_z)
                out[name] = lambda o=o, V=V: TracedModel(V, capture.drive, capture.brightness, **o)
        elif name == "lut":
            if (p, c) != (1, 3):
                out[name] = f"needs one RGB pattern, the capture has {p} pattern(s) x {c} channel(s)"
            else:
                out[name] = lambda o=o: LUTModel(**o)
        elif name == "mlp":
            scale = float(saturation) if saturation else 1.0
            # The sensor's own MLP settings (its profile's ensemble size) unless the caller set them.
            o = {**capture_model_options(capture).get("mlp", {}), **o}
            out[name] = lambda o=o, scale=scale: MLPModel(**{"input_scale": scale, **o})
        elif name in ("conv", "conv-fast"):
            scale = float(saturation) if saturation else 1.0
            if name == "conv" and ball_px is not None and "downsample" not in o:
                o = {**o, "downsample": ball_downsample(ball_px)}  # conv-fast keeps its fixed 2: the live cost
            out[name] = lambda o=o, scale=scale, cls=CONV_MODELS[name]: cls(**{"input_scale": scale, **o})
        else:
            raise UserError(f"calibrate: unknown model '{name}' (expected one of "
                            f"{', '.join(MODEL_NAMES + NEIGHBOURHOOD_MODELS)} or all)")
    return out


def calibrate(capture: Capture | str | Path, ball_radius_mm: float | None, mm_per_px: float | None = None,
              models: str | Sequence[str] = "all", *, illumination=None, folds: int = 5, shrink_px: float = 2.0,
              detect_options: DetectOptions | None = None, model_options: dict[str, dict] | None = None,
              refine_iterations: int = 2, refine_model: str = "auto", seed: int = 0,
              markers=None, tilt_correction: bool = True, circles="auto",
              gate: GateSettings | None = None) -> CalibrationResult:
    """Calibrate light models from a sphere-indentation capture.

    Parameters
    ----------
    capture : Capture or path
        Frames ``(K, P, H, W, C)``, reference ``(P, H, W, C)``, drive ``(P, L, 3)`` ...
        (``capture.h5`` layout).
    ball_radius_mm : float or None
        Radius of the pressed ball; None: the capture's ``ball_radius_mm`` attribute
        (``iristac import images --ball-radius``).
    mm_per_px : float, optional
        Pixel pitch; default: the capture's ``mm_per_px`` attribute.
    models : "all", a name, or a list of names
        Among ``far``, ``near``, ``traced``, ``lut``, ``mlp``, ``conv`` (the network,
        :class:`calibration.models.conv.ConvModel`: ``all`` fits it only when it is named beside
        it, ``["all", "conv"]``) and ``conv-fast`` (the network on the frame shrunk by 2,
        :class:`calibration.models.conv.ConvFastModel`, also fitted only when named). With ``all``, models that do not
        apply (``traced`` without ``illumination``, ``lut`` with more than one pattern) are
        reported as skipped; asked for by name they raise :class:`UserError`.
    illumination : IlluminationModel or ndarray (L, H, W, 3), optional
        LED fields for the traced model (:func:`read_illumination` reads one from a file).
        With ``model_options={"traced": {"correct_geometry": True}}`` (an IlluminationModel
        is then needed) the traced fit also corrects LED positions and tilts to first order
        (:mod:`calibration.models.led_geometry`).
    folds : int
        Cross-validation press groups.
    shrink_px : float
        Margin inside each contact circle excluded from fitting and validation.
    detect_options : DetectOptions, optional
        Contact detection and the drift removed from each press; default
        :func:`capture_detect_options` (the capture's sensor profile's drift model, else
        ``gain_offset``). The drift model used is recorded (``meta["circle_settings"]``) and
        :func:`calibration.evaluate.evaluate_calibration` removes the same from test presses.
    model_options : dict, optional
        name -> keyword arguments of that model's constructor (e.g. ``{"near": {"degree": 3}}``).
        The MLP's default is the capture's sensor profile's (:func:`capture_model_options`: the
        DIGIT's fits an ensemble of three nets); a key given here wins.
    refine_iterations : int
        Passes of :func:`calibration.refine.refine_centres` (photometric centres from
        cross-fitted normals); 0 keeps the edge detector's centres.
    refine_model : {"auto", "far", "near", "traced", "mlp"}
        The light model whose normals vote for the centres. ``auto``: ``traced`` when
        ``illumination`` is given (the ray-traced LED fields follow the lens; a polynomial
        near field cannot, and on the default lens scene its 15 deg error moved the centres
        the wrong way), else no refinement: the centres a fitted light model votes for are
        that model family's own convention (on the shared real frames near-, far- and
        MLP-refined centres differ by 1.5-2 px, and each family scores 3-4 deg better against
        its own refined truth), and on presses never seen, against the detector's circles,
        the truth-free ball fit and the hand labels, every model did better calibrated on
        unrefined circles (docs/calibration.md). Options come from ``model_options``.
    seed : int
    markers : None, "none", "auto", a mask image path or an (H, W) bool array
        Printed gel markers (:mod:`calibration.markers`): filled in before anything else and
        left out of the samples. None: the capture's own ``markers`` dataset, if any.
    gate : GateSettings, optional
        Thresholds of the quality gate (:mod:`calibration.gate`); the result's ``verdict``
        says whether it passed, and :meth:`CalibrationResult.save` refuses a failed one.
    tilt_correction : bool
        Scale each model's predicted tilt by the gain that undoes its shrinkage toward flat on
        held-out presses, and clip it to the tilts the truth covered (:func:`_correct_output`).
        Measured on the shared real frames (train presses 0-19, test 20-29; docs/calibration.md).
    circles : {"auto", "detected", "labels"} or list of Circle
        Where the contact circles (the truth the models are fitted to) come from. ``detected``:
        the edge detector, then centre refinement (``refine_iterations``). ``labels``: the
        capture's hand labels (``labels/center_xy``, ``labels/radius_px``; contact radius
        clamped to 0.95 x the ball's, :mod:`calibration.labels`), used as given: no
        refinement; a capture without labels is a :class:`UserError`. Models calibrated on
        labels learn the labeller's convention (on the shared real frames the labels sit about
        2 px off the detected contacts: docs/calibration.md). ``auto`` (default): ``detected``.
        A list of K :class:`calibration.detect.Circle`: those circles, as given.

    Returns
    -------
    CalibrationResult

    Raises
    ------
    UserError
        Missing scale, fewer than two usable presses (:class:`calibration.gate.CalibrationRefused`,
        with the diagnosis), or patterns with fewer than three independent light directions
        (only when the circles do explain the shading; otherwise the error says the circles
        or the reference are at fault).
    """
    from pipeline.base.threads import limit_threads

    # Small, many solves: a single BLAS thread is several times faster on a loaded machine
    # than threads that spin waiting for a core (see pyproject.toml).
    with limit_threads(blas=1):
        return _calibrate(capture, ball_radius_mm, mm_per_px, models, illumination=illumination, folds=folds,
                          shrink_px=shrink_px, detect_options=detect_options, model_options=model_options,
                          refine_iterations=refine_iterations, refine_model=refine_model, seed=seed,
                          markers=markers, tilt_correction=tilt_correction, circles=circles, gate=gate)


#: Models that can vote for contact centres (they predict normals from a few patterns).
REFINE_MODELS = ("auto", "far", "near", "traced", "mlp")


def _refine_factory(refine_model: str, cap: Capture, illumination, saturation, model_options):
    """``(name, factory)`` of the model that refinement fits (see :func:`calibrate`); ``(None, None)``: none."""
    if refine_model not in REFINE_MODELS:
        raise UserError(f"calibrate: --refine-model must be one of {', '.join(REFINE_MODELS)}, got {refine_model!r}")
    if refine_model == "auto" and illumination is None:
        return None, None
    name = "traced" if refine_model == "auto" else refine_model
    make = model_factories([name], cap, illumination, saturation, model_options)[name]
    if isinstance(make, str):
        raise UserError(f"calibrate: centre refinement with the '{name}' model is impossible: {make}")
    return name, make


@dataclass
class CircleFit:
    """The contact circles of a capture and the samples around them (:func:`find_circles`).

    Attributes
    ----------
    capture : Capture
    source : str
        The file name (or "capture") for messages.
    mm_per_px : float
    frames, reference : ndarray
        Linear frames ``(K, P, H, W, C)`` and reference ``(P, H, W, C)`` (dark removed).
    saturation : float or None
        Observations at or above this (linear) value are left out of the samples.
    circles : list of Circle
    samples : Samples
        Gathered around the (refined) circles.
    light_rank_ratio : float
    detect_seconds : float
    refine : dict
        :func:`calibration.refine.refine_centres`' report plus ``seconds`` and ``model``.
    markers : ndarray, shape (H, W), bool, or None
        Printed gel markers: filled in ``frames`` and ``reference``, absent from ``samples``.
    ball_radius_mm : float
    source_of_circles : str
        ``detected``, ``labels`` or ``given`` (see :func:`calibrate`'s ``circles``).
    detected : list of Circle
        The detector's circles (refined when ``circles`` are detected): what hand labels are compared with.
    drifts : list of pipeline.normals.drift.Drift
        Each press's drift against the reference (fitted outside its contact), already removed
        from ``frames``.
    mismatch : float or None
        Median over presses of the drift left after removal (RMS, non-contact pixels) over the
        press's contact contrast (RMS difference inside its circle): large when the reference
        does not match the presses (:data:`calibration.gate.MAX_MISMATCH`).
    explained : float or None
        :func:`calibration.gate.shading_explained` of the samples (None when not checked).
    reference_note : str
        Where the reference came from (the capture's ``reference_source`` attribute).
    options : DetectOptions
        The detection options used (the drift model removed among them).
    """

    capture: Capture
    source: str
    mm_per_px: float
    frames: np.ndarray
    reference: np.ndarray
    saturation: float | None
    circles: list[Circle]
    samples: Samples
    light_rank_ratio: float
    detect_seconds: float
    refine: dict[str, Any]
    markers: np.ndarray | None = None
    ball_radius_mm: float = 0.0
    source_of_circles: str = "detected"
    detected: list[Circle] = field(default_factory=list)
    drifts: list = field(default_factory=list)
    mismatch: float | None = None
    explained: float | None = None
    reference_note: str = ""
    options: DetectOptions = field(default_factory=DetectOptions)


def find_circles(capture: Capture | str | Path, ball_radius_mm: float, mm_per_px: float | None = None, *,
                 illumination=None, folds: int = 5, shrink_px: float = 2.0,
                 detect_options: DetectOptions | None = None, model_options: dict[str, dict] | None = None,
                 refine_iterations: int = 2, refine_model: str = "auto", seed: int = 0, markers=None,
                 circles="auto", strict: bool = True) -> CircleFit:
    """Detect and refine the contact circles of a sphere-indentation capture (the truth of calibration).

    The first half of :func:`calibrate` (same parameters): edge detection, the light-rank
    check, photometric centre refinement with a model cross-fitted on this capture's own
    presses (or the hand labels, ``circles="labels"``), and the samples around the circles.
    :func:`calibration.evaluate.evaluate_calibration` uses it for the circles of a test
    capture (without refinement: no light model shapes that truth).

    Each press's illumination drift against the reference is fitted outside its circle and
    removed from the returned ``frames`` (:func:`pipeline.normals.drift.remove_drift`; the model is
    ``detect_options.drift``), so samples, models and evaluation all see drift-free presses.

    ``strict=False`` (what :func:`calibration.evaluate.evaluate_calibration` uses on a test
    capture): no error for too few accepted presses and no light-rank check (nothing is fitted).

    Raises
    ------
    UserError
        Missing scale, fewer than two accepted presses, or fewer than three light directions
        (``strict`` only for the last two).
    """
    from pipeline.base.threads import limit_threads

    with limit_threads(blas=1):  # why: see calibrate
        return _find_circles(capture, ball_radius_mm, mm_per_px, illumination=illumination, folds=folds,
                             shrink_px=shrink_px, detect_options=detect_options, model_options=model_options,
                             refine_iterations=refine_iterations, refine_model=refine_model, seed=seed,
                             markers=markers, circles=circles, strict=strict)


def _circle_source(circles, k: int, src: str) -> str:
    """``detected``, ``labels`` or ``given`` for :func:`calibrate`'s ``circles`` argument (checked)."""
    if isinstance(circles, str):
        if circles not in CIRCLE_SOURCES:
            raise UserError(f"calibrate: --circles must be one of {', '.join(CIRCLE_SOURCES)}, got {circles!r}")
        return "detected" if circles == "auto" else circles
    given = list(circles)
    if len(given) != k or not all(isinstance(c, Circle) for c in given):
        raise UserError(f"{src}: circles must be 'auto', 'detected', 'labels' or {k} Circle records (one per press), "
                        f"got {len(given)} item(s)")
    return "given"


def profile_detect_options(profile) -> DetectOptions:
    """Detection options removing a sensor profile's drift model (``calibration_drift``; a name, a
    file or a SensorProfile), else :class:`calibration.detect.DetectOptions`' defaults.

    >>> profile_detect_options("digit").drift, profile_detect_options("gelsight-mini").drift
    ('field', 'gain_offset')
    """
    from pipeline.capture.sensor_profiles import load_profile

    drift = load_profile(profile).calibration_drift
    return DetectOptions(drift=drift) if drift else DetectOptions()


def capture_detect_options(capture: Capture) -> DetectOptions:
    """The detection options a capture is calibrated with when none are given: its sensor
    profile's drift model, else :class:`calibration.detect.DetectOptions`' defaults.

    ``import images --profile`` records the profile's name (``sensor_profile``) and its drift
    model (``calibration_drift``, when the profile names one). The recorded model is used; a
    capture that names a built-in profile but records none (imported before the model was
    recorded) gets that profile's (:func:`pipeline.capture.sensor_profiles.capture_setting`).

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> capture_detect_options(SimpleNamespace(meta={"sensor_profile": "lab-gel", "calibration_drift": "field"})).drift
    'field'
    >>> capture_detect_options(SimpleNamespace(meta={"sensor_profile": "digit"})).drift
    'field'
    >>> capture_detect_options(SimpleNamespace(meta={})).drift
    'gain_offset'
    """
    from pipeline.capture.sensor_profiles import capture_setting

    drift = capture_setting(getattr(capture, "meta", None) or {}, "calibration_drift")
    return DetectOptions(drift=str(drift)) if drift else DetectOptions()


def profile_model_options(profile) -> dict[str, dict]:
    """Model options a sensor profile sets (a name, a file or a SensorProfile): ``{"mlp":
    {"members": N}}`` from its ``calibration_mlp_members``, else ``{}``.

    >>> profile_model_options("digit"), profile_model_options("gelsight-mini")
    ({'mlp': {'members': 3}}, {})
    """
    from pipeline.capture.sensor_profiles import load_profile

    members = load_profile(profile).calibration_mlp_members
    return {"mlp": {"members": int(members)}} if members else {}


def capture_model_options(capture: Capture) -> dict[str, dict]:
    """The model options a capture is calibrated with unless the caller gives them: its sensor
    profile's ensemble size (``calibration_mlp_members``) as recorded at import, else the
    built-in profile's it names (:func:`pipeline.capture.sensor_profiles.capture_setting`), else none.

    Examples
    --------
    >>> from types import SimpleNamespace
    >>> capture_model_options(SimpleNamespace(meta={"sensor_profile": "lab-gel", "calibration_mlp_members": 5}))
    {'mlp': {'members': 5}}
    >>> capture_model_options(SimpleNamespace(meta={"sensor_profile": "digit"}))
    {'mlp': {'members': 3}}
    >>> capture_model_options(SimpleNamespace(meta={}))
    {}
    """
    from pipeline.capture.sensor_profiles import capture_setting

    members = capture_setting(getattr(capture, "meta", None) or {}, "calibration_mlp_members")
    return {"mlp": {"members": int(members)}} if members else {}


def _find_circles(capture, ball_radius_mm, mm_per_px, *, illumination, folds, shrink_px, detect_options,
                  model_options, refine_iterations, refine_model, seed, markers=None, circles="auto",
                  strict=True) -> CircleFit:
    src = str(capture) if not isinstance(capture, Capture) else "capture"
    cap = read_capture(capture) if not isinstance(capture, Capture) else capture
    mm = mm_per_px if mm_per_px is not None else cap.mm_per_px
    if mm is None or isinstance(mm, (str, bytes, list, tuple)) or not mm > 0:
        raise UserError(f"{src}: no mm_per_px attribute and no --mm-per-px given (expected a positive pixel pitch, "
                        f"got {mm!r})")
    if ball_radius_mm is None:
        ball_radius_mm = cap.meta.get("ball_radius_mm")
        if ball_radius_mm is None:
            raise UserError(f"{src}: no ball_radius_mm attribute and no --ball-radius given (the pressed ball's "
                            "radius in mm)")
    ball_radius_mm = float(ball_radius_mm)
    if not ball_radius_mm > 0:
        raise UserError(f"calibrate: --ball-radius must be a positive radius in mm, got {ball_radius_mm}")
    source = _circle_source(circles, int(np.asarray(cap.frames).shape[0]), src)
    ball_px = ball_radius_mm / mm
    if source == "labels":  # before any work: a clear error when the capture has none
        labelled = capture_label_circles(cap, ball_px, src)
    frames, ref = cap.linear()
    sat = {np.dtype(np.uint8): 255.0, np.dtype(np.uint16): 65535.0}.get(np.asarray(cap.frames).dtype)
    if sat is not None and cap.dark is not None:
        sat = sat - float(np.asarray(cap.dark).min())
    mask = _marker_mask(markers, cap, ref)
    press_mask = None
    if mask is not None:
        from calibration.markers import press_markers
        from pipeline.normals.prepare import fill_markers

        # Each press filled where its own dots are (they move with the gel under the press), the
        # reference wherever any press has one: no pixel is filled in one and not the other.
        press_mask = press_markers(frames, mask)
        frames, ref = fill_markers(frames, press_mask), fill_markers(ref, press_mask.any(axis=0))
    opt = detect_options or capture_detect_options(cap)
    t0 = time.perf_counter()
    # The detector runs in every mode: with labels or given circles its circles are what
    # they are compared with (the report's centre offset), not what is fitted.
    detected = detect_contacts(frames, ref, ball_px, opt, exclude=mask if press_mask is None else press_mask)
    shading_report = None
    if opt.shading:
        first, _ = _without_drift(frames, ref, detected, detected, ball_px, opt, mask, sat)
        detected, shading_report = refit_by_shading(first, ref, detected, ball_px, opt,
                                                    exclude=mask if press_mask is None else press_mask,
                                                    saturation=sat)
    t_detect = time.perf_counter() - t0
    use = {"detected": detected, "labels": labelled if source == "labels" else None,
           "given": None if isinstance(circles, str) else list(circles)}[source]
    frames, drifts = _without_drift(frames, ref, use, detected, ball_px, opt, mask, sat)
    accepted = sum(c.accepted for c in use)
    if accepted < 2 and strict:
        verdict = judge(use, best_model=None, cv_deg=None, ball_radius_error=None, source_of_circles=source)
        raise CalibrationRefused(verdict.message(src), verdict, use)
    samples = collect_samples(frames, ref, use, ball_radius_mm, mm, shrink_px=shrink_px, saturation=sat,
                              exclude=mask)
    explained = None
    rank = float("nan")
    if strict:
        # Before any light model is fitted: refinement fits one, which needs three directions.
        rank, explained = _light_rank(cap, samples.subset(samples.press >= 0), src)
    t0 = time.perf_counter()
    refine_name, make_refine = (None, None) if source != "detected" else \
        _refine_factory(refine_model, cap, illumination, sat, model_options)
    if make_refine is None or refine_iterations <= 0:
        # Labels (or given circles) are the user's truth, used as given: refinement would move
        # them toward a light model's idea of the centres. Detected circles without a traced
        # model are not refined by default either (see calibrate's refine_model).
        why = (f"{source} circles used as given" if source != "detected" else
               "no refinement asked for" if refine_iterations <= 0 else
               "refine_model auto without an illumination model: the detector's circles")
        refine_report = {"iterations": 0, "median_move_px": [], "kept_detected": [], "model": None, "note": why}
    else:
        use, refine_report = refine_centres(frames, ref, use, ball_radius_mm, mm, iterations=refine_iterations,
                                            folds=folds, seed=seed, shrink_px=shrink_px, saturation=sat,
                                            make_model=make_refine, exclude=mask)
        refine_report["model"] = refine_name
        detected = use
        samples = collect_samples(frames, ref, use, ball_radius_mm, mm, shrink_px=shrink_px, saturation=sat,
                                  exclude=mask)
    refine_report["seconds"] = time.perf_counter() - t0
    refine_report["shading"] = shading_report
    return CircleFit(cap, src, float(mm), frames, ref, sat, use, samples, rank, t_detect, refine_report, mask,
                     ball_radius_mm, source, detected, drifts, _mismatch(frames, ref, use, drifts), explained,
                     str(cap.meta.get("reference_source") or "the capture's no-contact frame"), opt)


#: A far-field fit of the samples whose ``sigma_3 / sigma_1`` is below this is looked into (see :func:`_light_rank`).
MIN_LIGHT_RATIO = 0.05


def _light_rank(cap: Capture, samples: Samples, src: str) -> tuple[float, float]:
    """``(ratio, explained)`` of the far-field fit of the samples; raises only for lighting that is degenerate.

    Degenerate by design (:func:`calibration.gate.drive_light_ratio` of the drive) or in the
    data: a small ratio of a fit that *does* explain the shading (LEDs dark or on one line).
    A small ratio of a fit that explains little says nothing about the lights (misplaced
    circles, a reference that does not match, or a sensor whose lighting no far-field model
    describes, as the DIGIT's: 30 % explained with its contacts found right): the quality gate
    judges those calibrations by their models' errors instead.
    """
    from calibration.gate import DRIVE_MIN_RATIO, MIN_EXPLAINED, drive_light_ratio

    m = samples.flat_observations.shape[1]
    by_design = drive_light_ratio(cap.drive) if m >= 3 else 0.0
    if by_design < DRIVE_MIN_RATIO:
        lit = int((np.asarray(cap.drive) > 0).any(axis=2).any(axis=0).sum())
        raise UserError(f"{src}: the lighting patterns span fewer than three independent light directions (the drive "
                        f"lights {lit} LED(s) giving {m} pattern-channel(s); on the ring their directions' smallest/"
                        f"largest singular value is {by_design:.2g} < {DRIVE_MIN_RATIO}); use LEDs around the ring, "
                        "not only on one diameter")
    ratio, explained = shading_explained(samples)
    if ratio < MIN_LIGHT_RATIO and explained >= MIN_EXPLAINED:
        check_light_rank(samples, MIN_LIGHT_RATIO, what=src)  # raises: the lights really are degenerate
    return ratio, explained


def _without_drift(frames, ref, use, detected, ball_px, opt: DetectOptions, mask, sat):
    """Each press's drift fitted outside its circle (the used one, else the detector's) and removed;
    saturated observations stay at the saturation level (so they are still left out)."""
    from pipeline.normals.drift import remove_drift

    where = [u if (u.accepted or not d.radius_px) else d for u, d in zip(use, detected)]
    corrected, drifts = remove_drift(frames, ref, where, ball_px, model=opt.drift, degree=opt.drift_degree,
                                     stripes=opt.stripes, exclude=mask)
    if sat is not None:
        corrected[frames >= sat] = sat
    return corrected, drifts


def _mismatch(frames, ref, circles, drifts) -> float | None:
    """Median over accepted presses of the drift left after removal over the contact's own contrast."""
    h, w = ref.shape[1:3]
    yy, xx = np.mgrid[:h, :w]
    ratios = []
    for k, (c, d) in enumerate(zip(circles, drifts)):
        if not c.accepted or c.contact_radius_px <= 0:
            continue
        inside = np.hypot(xx - c.center_xy[0], yy - c.center_xy[1]) < c.contact_radius_px
        if inside.any():
            contrast = float(np.sqrt(np.mean((frames[k][:, inside] - ref[:, inside]) ** 2)))
            ratios.append(d.residual_dn / max(contrast, 1e-9))
    return float(np.median(ratios)) if ratios else None


def _marker_mask(markers, cap: Capture, reference: np.ndarray) -> np.ndarray | None:
    """The marker mask to use: ``None`` -> the capture's own, ``"none"`` -> none, else
    :func:`calibration.markers.resolve_markers` (``"auto"``, a mask image, an array)."""
    if markers is None:
        return cap.markers
    from calibration.markers import resolve_markers

    return resolve_markers(markers, reference)


def _correct_output(model: CalibrationModel, cv: dict[str, Any], oof, samples: Samples, balls=None
                    ) -> dict[str, Any]:
    """Set the model's tilt gain and tilt limit; CV report of the result.

    The limit keeps answers within the tilts the truth covered (beyond them, at the rim and in
    the bulge, a model only extrapolates). The gain: the one that makes the model's
    reconstructions of held-out presses the ball's size (:mod:`calibration.ball_gain`, from
    ``balls``), falling back, when too few spheres were fitted, to the one that undoes the
    shrinkage toward flat of its out-of-fold predictions
    (:func:`calibration.models.base.fit_tilt_gain`: a least-squares fit dominated by the steep
    rim, where a blurred image shrinks the tilts most; on the DIGIT frames it made the middle of
    every cap too steep, spheres 13 % too small). A model whose
    :attr:`~calibration.models.base.CalibrationModel.applies_tilt_gain` is False keeps a gain of 1
    (``tilt_gain_source`` "none"), both gains still reported. The CV report's errors become those of
    the corrected predictions; the uncorrected mean is kept as
    ``cv_uncorrected_mean_angular_error_deg``, the ball figures as ``ball_gain``.
    """
    pred, valid, evaluated = oof
    use = evaluated & valid
    truth_tilt = np.hypot(samples.normals[samples.contact, 0], samples.normals[samples.contact, 1])
    model.max_tilt = float(min(0.999, 1.05 * truth_tilt.max())) if truth_tilt.size else None
    regression = fit_tilt_gain(pred[use, :2], samples.normals[use, :2]) if use.any() else 1.0
    ball = balls.gain(model.max_tilt) if balls is not None else None
    if not model.applies_tilt_gain:  # measured and reported, not applied (the family's own reason)
        source, model.tilt_gain = "none", 1.0
    elif ball is not None and ball["gain"] is not None:
        source, model.tilt_gain = "ball", ball["gain"]
    else:
        source, model.tilt_gain = "regression", regression
    corrected, _ = scale_tilt(pred, model.tilt_gain, model.max_tilt)
    errors = np.full(len(samples), np.nan)
    e = angular_error_deg(corrected, samples.normals)
    errors[evaluated] = np.where(valid & np.isfinite(e), e, INVALID_ERROR_DEG)[evaluated]
    out = cv_report(errors, samples, cv["folds"])
    out["cv_uncorrected_mean_angular_error_deg"] = cv["cv_mean_angular_error_deg"]
    out["tilt_gain"] = model.tilt_gain
    out["tilt_gain_source"] = source
    out["regression_tilt_gain"] = regression
    out["max_tilt"] = model.max_tilt
    if ball is not None:
        out["ball_gain"] = ball
    return out


def _calibrate(capture, ball_radius_mm, mm_per_px, models, *, illumination, folds, shrink_px, detect_options,
               model_options, refine_iterations, refine_model, seed, markers=None,
               tilt_correction=True, circles="auto", gate=None) -> CalibrationResult:
    names = [models] if isinstance(models, str) else list(models)
    explicit = "all" not in names
    if not explicit:  # "all": the per-pixel models, and the network when named beside it
        names = list(MODEL_NAMES) + [n for n in names if n in NEIGHBOURHOOD_MODELS]
    found = _find_circles(capture, ball_radius_mm, mm_per_px, illumination=illumination, folds=folds,
                          shrink_px=shrink_px, detect_options=detect_options, model_options=model_options,
                          refine_iterations=refine_iterations, refine_model=refine_model, seed=seed,
                          markers=markers, circles=circles)
    cap, mm, ref, sat, circles, samples = (found.capture, found.mm_per_px, found.reference, found.saturation,
                                           found.circles, found.samples)
    ball_radius_mm = found.ball_radius_mm
    frames, rank, t_detect, refine_report = found.frames, found.light_rank_ratio, found.detect_seconds, found.refine
    factories = model_factories(names, cap, illumination, sat, model_options, ball_px=ball_radius_mm / mm)
    fitted: dict[str, CalibrationModel] = {}
    reports: dict[str, dict[str, Any]] = {}
    for name, make in factories.items():
        if isinstance(make, str):
            if explicit:
                raise UserError(f"calibrate: model '{name}' cannot be fitted: {make}")
            reports[name] = {"skipped": make}
            continue
        t = time.perf_counter()
        balls = OutOfFoldBalls(frames, ref, [k for k, c in enumerate(circles) if c.accepted], mm, ball_radius_mm,
                               folds, markers=found.markers,
                               contacts=[(*c.center_xy, c.radius_px) for c in circles]) if tilt_correction else None
        cv, oof = cross_validate(make, samples, ref, folds=folds, seed=seed, return_predictions=True,
                                 fold_hook=balls)
        model = make()
        fit = model.fit(samples, ref)
        if tilt_correction:
            cv = _correct_output(model, cv, oof, samples, balls)
        reports[name] = {"fit": fit, "cv": cv, "seconds": time.perf_counter() - t,
                         "problems": model_problems(cv, gate)}
        fitted[name] = model
    labels = None
    if has_labels(cap):
        # The detector's circles against the labels (with labels as the truth, how far the
        # user's labels sit from what the detector sees).
        labels = label_errors(found.detected, cap.labels["center_xy"], cap.labels["radius_px"])
    best = _best(reports)
    ball = _ball_summary(best, reports)
    best_cv = reports[best]["cv"] if best is not None else {}
    verdict = judge(circles, best_model=best, cv_deg=best_cv.get("cv_answered_mean_angular_error_deg"),
                    cv_invalid=best_cv.get("invalid_fraction"), explained=found.explained,
                    ball_radius_error=None if ball is None else ball["raw_radius_error"],
                    mismatch=found.mismatch, source_of_circles=found.source_of_circles, settings=gate)
    drift = _drift_summary(found)
    return CalibrationResult(circles=circles, models=fitted, reports=reports, labels=labels, verdict=verdict,
                             ball_radius_mm=float(ball_radius_mm), mm_per_px=float(mm), shape=cap.shape,
                             num_patterns=int(frames.shape[1]), num_channels=int(frames.shape[4]),
                             light_rank_ratio=rank,
                             meta={"detect_seconds": t_detect, "refine": refine_report, "samples": len(samples),
                                   "contact_samples": int(samples.contact.sum()),
                                   "circle_settings": {"circles": found.source_of_circles,
                                                       "refine_model": refine_report["model"],
                                                       "refine_iterations": int(refine_report["iterations"]),
                                                       "shrink_px": float(shrink_px), "folds": int(folds),
                                                       **drift_settings(found.options)},
                                   "reference": found.reference_note, "drift": drift,
                                   **({"ball_fit": ball} if ball is not None else {})},
                             markers=found.markers)


def _ball_summary(best: str | None, reports: dict[str, dict[str, Any]]) -> dict[str, Any] | None:
    """The best model's truth-free ball fit on held-out presses (:mod:`calibration.ball_gain`), or None."""
    if best is None:
        return None
    ball = (reports[best].get("cv") or {}).get("ball_gain")
    if not ball or ball.get("raw_radius_error") is None:
        return None
    return {"model": best, **ball, "applied": reports[best]["cv"].get("tilt_gain_source") == "ball"}


def _drift_summary(found: CircleFit) -> dict[str, Any]:
    """How far the presses drifted from the reference and how much of it the drift model removed."""
    ds = found.drifts
    if not ds:
        return {}
    gains = np.array([d.gain[..., 0] for d in ds])
    offsets = np.array([d.offset[..., 0] for d in ds])
    return {"model": ds[0].model, "reference": found.reference_note,
            "max_abs_offset_dn": float(np.abs(offsets).max()), "max_abs_gain_change": float(np.abs(gains - 1).max()),
            "before_dn_median": float(np.median([d.before_dn for d in ds])),
            "residual_dn_median": float(np.median([d.residual_dn for d in ds])),
            "mismatch": found.mismatch, "per_press": [d.summary() for d in ds]}
