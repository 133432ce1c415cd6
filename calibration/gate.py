"""Is a calibration worth writing? The quality gate, and the diagnosis of one that is not.

A calibration is refused (``iristac calibrate`` exits non-zero and writes nothing unless
``--force``; :meth:`calibration.calibrate.CalibrationResult.save` raises
:class:`CalibrationRefused`) when

- fewer than :data:`MIN_ACCEPTED` presses were accepted,
- its best model's cross-validated error exceeds :data:`MAX_CV_DEG`, or
- a sphere fitted to its best model's reconstruction of its own presses (the truth-free ball
  fit, :mod:`calibration.ballfit`) is more than :data:`MAX_BALL_RADIUS_ERROR` off the ball.

The thresholds come from measurements (docs/calibration.md, "Quality gate"). The refusal
names the likely cause, from the evidence the calibration gathered on the way, and what to
do next:

- **contacts not found**: most presses rejected by the detector (their reasons are listed);
- **reference mismatch**: the presses differ from the no-contact reference away from the
  contacts by more than the drift model removes (a reference taken under other light, of
  another gel or crop);
- **too few presses**: the detector accepted what it was given, there is just too little;
- **contacts misplaced**: circles accepted, but the contact geometry they imply does not
  explain the colour changes (:func:`shading_explained`);
- **shape**: models that agree with the circles (low CV) but reconstruct presses that are not
  the ball's shape (circles wider or narrower than the contacts).

A ball radius or pixel pitch that is wrong by a constant factor escapes every check here: the
truth normals are then those of a consistent sphere of the stated radius, which the models
learn and reconstruct (measured: a 3 mm ball declared for the 2 mm one of the shared GelSight
frames calibrates with CV 4.1 deg and a ball fit 1.7 % off); only a known object shows it.
- **degenerate lighting**: only when the circles do explain the shading and the light
  directions still span fewer than three dimensions.

Every model is also judged on its own (:func:`model_problems`): a model with no valid
prediction on held-out presses, a CV error beyond :data:`MAX_CV_DEG`, or reconstructions of
held-out presses that are no ball (the sphere fit more than :data:`MAX_BALL_RADIUS_ERROR` off,
or no bump to fit) is marked unusable in the calibration's report, the calibrate and eval
tables and the benchmarks, and is not chosen as the best model; its figures are not results.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipeline.base.errors import UserError

__all__ = [
    "DRIVE_MIN_RATIO",
    "MAX_BALL_RADIUS_ERROR",
    "MAX_CV_DEG",
    "MAX_MISMATCH",
    "MIN_ACCEPTED",
    "MIN_EXPLAINED",
    "NEXT_LABEL",
    "NEXT_MORE",
    "NEXT_OVERLAY",
    "NEXT_REFERENCE",
    "NEXT_SCALE",
    "CalibrationRefused",
    "GateSettings",
    "Verdict",
    "drive_light_ratio",
    "judge",
    "model_problems",
    "rank_message",
    "shading_explained",
]

#: Fewest accepted presses a calibration is written from (docs/calibration.md, "Quality gate").
MIN_ACCEPTED = 6
#: Largest cross-validated mean error of the best model (degrees), over the held-out contact
#: pixels it answers.
MAX_CV_DEG = 20.0
#: Largest fraction of the held-out contact pixels the best model leaves unanswered (a lookup
#: table has no entry for a colour it never saw). Measured: 0.01 for the shared GelSight's LUT
#: (20 presses); 0.32-0.58 for LUTs of 24 to 6 rendered presses of 4-5 px contacts (60 x 80 px,
#: the quick demo), which still reconstruct its test object at 2.2 deg on 92 % of the pixels;
#: a model that answers fewer than one held-out pixel in four is refused.
MAX_CV_INVALID = 0.75
#: Largest median relative error of the truth-free ball fit of the best model.
MAX_BALL_RADIUS_ERROR = 0.20
#: Below this fraction of the contact pixels' colour variance explained by the far-field fit of
#: the circles' sphere caps, the circles (or the reference), not the lights, are at fault.
MIN_EXPLAINED = 0.7
#: Above this ratio of the drift left after removal (RMS, non-contact pixels) to the contacts'
#: own contrast, the reference does not match the presses. Measured: 0.14-0.19 on the shared
#: GelSight and DIGIT frames (drift removed, also with 28 DN and 15 % added to every press), 0.41
#: with 28 DN added and the drift left in.
MAX_MISMATCH = 0.3

NEXT_OVERLAY = "look at every press and its circle: iristac calibrate CAPTURE.h5 --out CAL.h5 --overlay overlay.png"
NEXT_LABEL = ("draw the circles the detector missed in the browser: iristac label CAPTURE.h5, then iristac calibrate "
              "CAPTURE.h5 --circles labels")
NEXT_MORE = "capture more presses (20-50, spread over the gel, none touching the border) and import them again"
NEXT_REFERENCE = ("take a no-contact frame right before the presses with the same exposure and light, or import the "
                  "folder with --reference build (a reference built from the presses themselves)")
NEXT_SCALE = "check --ball-radius and --mm-per-px (the ball's radius in mm and the pixel pitch on the gel)"


class CalibrationRefused(UserError):
    """A calibration the quality gate refuses; ``verdict`` says why and what to do, ``circles`` (when
    known) are the press circles, for an overlay."""

    def __init__(self, message: str, verdict: Verdict, circles=None):
        super().__init__(message)
        self.verdict = verdict
        self.circles = circles


@dataclass
class GateSettings:
    """Thresholds of :func:`judge` (defaults: the module constants)."""

    min_accepted: int = MIN_ACCEPTED
    max_cv_deg: float = MAX_CV_DEG
    max_cv_invalid: float = MAX_CV_INVALID
    max_ball_radius_error: float = MAX_BALL_RADIUS_ERROR


@dataclass
class Verdict:
    """What :func:`judge` found.

    Attributes
    ----------
    passed : bool
    problems : list of str
        What is wrong, with numbers (empty when passed).
    cause : str
        The likely cause, in words ("" when passed).
    next_steps : list of str
    evidence : dict
        The figures the diagnosis rests on.
    """

    passed: bool
    problems: list[str] = field(default_factory=list)
    cause: str = ""
    next_steps: list[str] = field(default_factory=list)
    evidence: dict[str, Any] = field(default_factory=dict)

    def message(self, source: str = "calibration") -> str:
        """One paragraph: refused, what, why, next."""
        if self.passed:
            return f"{source}: passes the quality gate"
        steps = "; ".join(f"({i + 1}) {s}" for i, s in enumerate(self.next_steps))
        return (f"{source}: calibration refused: {'; '.join(self.problems)}. Likely cause: {self.cause}. "
                f"Next: {steps}. (--force writes it anyway.)")

    def to_dict(self) -> dict[str, Any]:
        return {"passed": self.passed, "problems": list(self.problems), "cause": self.cause,
                "next_steps": list(self.next_steps), "evidence": self.evidence}


def shading_explained(samples) -> tuple[float, float]:
    """``(rank_ratio, explained)`` of the linear far-field fit ``I_m = a_m + n . L_m`` of the samples.

    ``rank_ratio`` is ``sigma_3 / sigma_1`` of the fitted ``L (M, 3)``; ``explained`` the
    fraction of the contact pixels' observation variance the fit explains (R^2). Circles in
    the wrong place give truth normals unrelated to the colours: little is explained, and the
    fitted light matrix is small and ill-conditioned *whatever the lights*. Measured: 0.82
    (shared GelSight frames, detected circles), 0.93 (rendered full ring), 0.88 (rendered LEDs on
    one diameter only: degenerate, yet explained), 0.50 (GelSight presses drifted by 20-28 DN
    against their reference, circles then detected 10-40 px off).
    """
    obs = samples.flat_observations.astype(np.float64)
    A = np.concatenate([np.ones((len(samples), 1)), samples.normals], axis=1)
    coef = np.linalg.lstsq(A, obs, rcond=None)[0]  # (4, M)
    s = np.linalg.svd(coef[1:].T, compute_uv=False)
    ratio = float(s[-1] / max(s[0], 1e-30))
    c = np.asarray(samples.contact, bool)
    if not c.any():
        return ratio, 0.0
    res = obs[c] - A[c] @ coef
    tot = obs[c] - obs[c].mean(axis=0)
    explained = float(1.0 - (res ** 2).sum() / max((tot ** 2).sum(), 1e-30))
    return ratio, explained


#: A drive whose nominal light directions have ``sigma_3 / sigma_1`` below this is degenerate by design.
DRIVE_MIN_RATIO = 0.01


def drive_light_ratio(drive: np.ndarray, ring_radius_mm: float = 40.0, gel_z_mm: float = 30.0) -> float:
    """``sigma_3 / sigma_1`` of the light directions a drive matrix gives on the nominal ring.

    LED ``i`` of ``L`` sits on a ring (:func:`sim.point_source.ring_geometry`); pattern ``p``,
    channel ``c`` lights the gel centre from ``sum_i drive[p, i, c] (led_i - centre) / |led_i - centre|``.
    No data is involved: a drive that lights only LEDs on one diameter (or fewer than three
    pattern-channels) is degenerate whatever the frames show. An imported sensor's drive of
    three colour groups counts as three LEDs 120 degrees apart.

    Examples
    --------
    >>> one_diameter = np.zeros((2, 6, 3)); one_diameter[0, 0] = 1; one_diameter[1, 3] = 1
    >>> drive_light_ratio(one_diameter) < 1e-9, drive_light_ratio(np.eye(3)[None]) > 0.5
    (True, True)
    """
    from sim.point_source import ring_geometry

    d = np.asarray(drive, np.float64)
    if d.ndim != 3 or d.shape[2] < 1:
        raise ValueError(f"drive_light_ratio: drive must be (P, L, C), got {d.shape}")
    pos, _ = ring_geometry(d.shape[1], ring_radius_mm)
    to_led = pos - np.array([0.0, 0.0, gel_z_mm])
    to_led /= np.linalg.norm(to_led, axis=1, keepdims=True)
    lights = np.einsum("plc,lk->pck", d, to_led).reshape(-1, 3)
    if len(lights) < 3:
        return 0.0
    s = np.linalg.svd(lights, compute_uv=False)
    return float(s[-1] / max(s[0], 1e-30))


def rank_message(what: str, singular: np.ndarray, ratio: float, min_ratio: float, explained: float) -> str:
    """The error for a failed light-rank check: degenerate lighting only when the circles explain the shading."""
    sv = np.round(np.asarray(singular) / max(float(singular[0]), 1e-30), 4).tolist()
    if explained >= MIN_EXPLAINED:
        return (f"{what}: the lighting patterns span fewer than three independent light directions (singular values "
                f"of the fitted light matrix {sv}, smallest/largest {ratio:.4f} < {min_ratio}; the contact circles "
                f"explain {explained:.0%} of the shading, so the circles are not at fault); use LEDs around the "
                "ring, not only on one diameter")
    return (f"{what}: the contact circles do not explain the shading (a far-field fit of their sphere caps explains "
            f"{explained:.0%} of the colour change inside them, < {MIN_EXPLAINED:.0%}; its light matrix, smallest/"
            f"largest singular value {ratio:.4f}, says nothing about the lights). Likely cause: contacts misplaced "
            "or a reference that does not match the presses, not the lighting. Next: (1) "
            f"{NEXT_OVERLAY}; (2) {NEXT_LABEL}; (3) {NEXT_REFERENCE}")


def model_problems(cv: dict[str, Any] | None, settings: GateSettings | None = None) -> list[str]:
    """Why one fitted model's depth maps are not to be used (empty: usable), from its CV report.

    ``cv`` is the model's cross-validation report (``cv_mean_angular_error_deg``,
    ``invalid_fraction`` and, with the tilt correction, ``ball_gain``: the truth-free ball fit of
    its reconstructions of held-out presses, :mod:`calibration.ball_gain`). The thresholds are
    the quality gate's (:class:`GateSettings`).

    Examples
    --------
    >>> model_problems({"cv_mean_angular_error_deg": 6.0, "invalid_fraction": 0.0,
    ...                 "ball_gain": {"raw_radius_error": 0.03, "presses": 10}})
    []
    >>> model_problems({"cv_mean_angular_error_deg": 90.0, "invalid_fraction": 1.0})
    ['no valid prediction on the held-out presses']
    >>> model_problems({"cv_mean_angular_error_deg": 19.0, "invalid_fraction": 0.0,
    ...                 "ball_gain": {"raw_radius_error": 1.5, "presses": 10}})
    ['its reconstructions of held-out presses are spheres 150% off the ball (> 20%)']
    """
    st = settings or GateSettings()
    if not cv:
        return ["not cross-validated"]
    if (cv.get("invalid_fraction") or 0.0) >= 1.0:
        return ["no valid prediction on the held-out presses"]
    out = []
    # Judged like the gate judges the best model: the error over the pixels it answers, and the
    # share it leaves unanswered on its own (a LUT with empty bins is not 90 deg wrong there).
    deg = cv.get("cv_answered_mean_angular_error_deg", cv.get("cv_mean_angular_error_deg"))
    if deg is not None and deg > st.max_cv_deg:
        out.append(f"CV error {deg:.1f} deg (> {st.max_cv_deg:g})")
    invalid = cv.get("invalid_fraction")
    if invalid is not None and invalid > st.max_cv_invalid:
        out.append(f"leaves {invalid:.0%} of the held-out presses' contact pixels unanswered (> {st.max_cv_invalid:.0%})")
    ball = cv.get("ball_gain") or {}
    raw = ball.get("raw_radius_error")
    if raw is not None and abs(raw) > st.max_ball_radius_error:
        out.append(f"its reconstructions of held-out presses are spheres {abs(raw):.0%} off the ball "
                   f"(> {st.max_ball_radius_error:.0%})")
    elif raw is None and ball.get("attempted", 0) >= 3:
        out.append(f"its reconstructions of held-out presses show no ball ({ball.get('note') or 'no sphere fitted'})")
    return out


def _rejection_summary(circles) -> str:
    counts: dict[str, int] = {}
    for c in circles:
        if not c.accepted:
            key = c.reason.split(":")[0]
            counts[key] = counts.get(key, 0) + 1
    return ", ".join(f"{n} {k}" for k, n in sorted(counts.items(), key=lambda kv: -kv[1]))


def judge(circles, *, best_model: str | None, cv_deg: float | None, ball_radius_error: float | None,
          cv_invalid: float | None = None, explained: float | None = None, mismatch: float | None = None, source_of_circles: str = "detected",
          settings: GateSettings | None = None) -> Verdict:
    """The quality gate on a calibration's figures, with the likely cause of a failure.

    Parameters
    ----------
    circles : list of Circle
        The circles the models were fitted to (``accepted``, ``reason``).
    best_model : str or None
    cv_deg : float or None
        The best model's cross-validated mean error over the held-out pixels it answers.
    ball_radius_error : float or None
        Median relative error of the best model's truth-free ball fit on the calibration's presses.
    cv_invalid : float, optional
        The fraction of held-out contact pixels the best model left unanswered.
    explained : float, optional
        :func:`shading_explained`'s fraction.
    mismatch : float, optional
        Drift left after removal over the contacts' contrast (median over presses).
    source_of_circles : str
        ``detected``, ``labels`` or ``given``.
    settings : GateSettings, optional

    Examples
    --------
    >>> from calibration.detect import Circle
    >>> ok = [Circle((5.0, 5.0), 3.0, 3.0, 1.0, True, "ok")] * 10
    >>> judge(ok, best_model="mlp", cv_deg=7.0, ball_radius_error=0.02).passed
    True
    >>> bad = ok[:3] + [Circle((5.0, 5.0), 0.0, 0.0, 0.0, False, "too faint: peak contrast 3")] * 7
    >>> v = judge(bad, best_model="mlp", cv_deg=30.0, ball_radius_error=0.5)
    >>> v.passed, v.cause.startswith("contacts not found")
    (False, True)
    """
    st = settings or GateSettings()
    k = len(circles)
    accepted = int(sum(c.accepted for c in circles))
    evidence = {"presses": k, "accepted": accepted, "best_model": best_model, "cv_deg": cv_deg,
                "cv_invalid": cv_invalid,
                "ball_radius_error": ball_radius_error, "explained": explained, "mismatch": mismatch,
                "thresholds": {"min_accepted": st.min_accepted, "max_cv_deg": st.max_cv_deg,
                               "max_cv_invalid": st.max_cv_invalid,
                               "max_ball_radius_error": st.max_ball_radius_error, "min_explained": MIN_EXPLAINED,
                               "max_mismatch": MAX_MISMATCH}}
    problems = []
    if accepted < st.min_accepted:
        problems.append(f"only {accepted} of {k} presses accepted (at least {st.min_accepted} needed)")
    if cv_deg is None and accepted >= st.min_accepted:
        problems.append("no model gave a valid cross-validated error")
    elif cv_deg is not None and cv_deg > st.max_cv_deg:
        problems.append(f"the best model ({best_model}) has a CV error of {cv_deg:.1f} deg (> {st.max_cv_deg:g})")
    uncovered = cv_invalid is not None and cv_invalid > st.max_cv_invalid
    if uncovered:
        problems.append(f"the best model ({best_model}) leaves {cv_invalid:.0%} of the held-out presses' contact pixels "
                        f"unanswered (> {st.max_cv_invalid:.0%})")
    if ball_radius_error is not None and abs(ball_radius_error) > st.max_ball_radius_error:
        problems.append(f"a sphere fitted to its reconstruction of the presses is {abs(ball_radius_error):.0%} off "
                        f"the ball's radius (> {st.max_ball_radius_error:.0%})")
    if not problems:
        return Verdict(True, evidence=evidence)
    rejected = k - accepted
    if mismatch is not None and mismatch > MAX_MISMATCH:
        cause = (f"reference mismatch: away from the contacts the presses still differ from the no-contact reference "
                 f"by {mismatch:.0%} of the contacts' own contrast after what the drift model removes")
        steps = [NEXT_REFERENCE, NEXT_OVERLAY]
    elif accepted < st.min_accepted and rejected > 0 and rejected >= accepted:
        cause = (f"contacts not found: the detector rejected {rejected} of {k} presses ({_rejection_summary(circles)})"
                 if source_of_circles == "detected" else
                 f"{rejected} of {k} {source_of_circles} circles unusable")
        steps = [NEXT_OVERLAY, NEXT_LABEL, NEXT_SCALE]
    elif accepted < st.min_accepted:
        cause = f"too few presses: {accepted} accepted of {k} given"
        steps = [NEXT_MORE, NEXT_OVERLAY]
    elif uncovered and len(problems) == 1:
        cause = (f"too few presses to cover the colours: each held-out press shows colours (contact tilts) that "
                 f"the {best_model} fitted to the others never saw")
        steps = [NEXT_MORE, NEXT_OVERLAY]
    elif explained is not None and explained < MIN_EXPLAINED:
        cause = (f"contacts misplaced: the circles' sphere caps explain only {explained:.0%} of the colour change "
                 "inside them")
        steps = [NEXT_OVERLAY, NEXT_LABEL, NEXT_REFERENCE]
    elif (ball_radius_error is not None and abs(ball_radius_error) > st.max_ball_radius_error
          and cv_deg is not None and cv_deg <= 0.5 * st.max_cv_deg
          and (explained is None or explained >= MIN_EXPLAINED)):
        cause = ("shape: the models agree with the circles, but what they reconstruct is not the ball's shape (circles "
                 "drawn wider or narrower than the contacts, or a ball radius that is not the one pressed)")
        steps = [NEXT_SCALE, NEXT_OVERLAY]
    else:
        cause = "contacts misplaced or too few presses to pin the models (the circles and the shading disagree)"
        steps = [NEXT_OVERLAY, NEXT_LABEL, NEXT_MORE]
    return Verdict(False, problems, cause, steps, evidence)
