"""A new unit calibrated from a few presses and another unit's calibration (the prior).

Units of one sensor model differ in their LEDs' brightness and colour, their gel and where the
camera sits against the lights; the shape of the colour-to-normal mapping is the design's. So
the prior's MLP (:class:`calibration.models.mlp.MLPModel`) is kept, frozen, and only a small
affine map of its inputs is fitted on the new unit's presses (:func:`adapt_mlp`):

- per pattern, a 3 x 3 colour matrix ``M`` on the colour change and the reference colour, and a
  colour offset ``c`` on the reference colour (``d' = M d``, ``r' = M r + c``): the new unit's
  colours as the prior's unit would have seen them;
- a 2 x 2 matrix and an offset on the normalised pixel position (a camera a little off).

The map is then folded into the network's first layer (``W' = W T``, ``b' = b + W s``), so the
adapted model is a plain MLP: ``calibration.h5`` is a normal calibration that ``reconstruct``
and ``live --calibration`` use as is. Then (``finetune_steps``, 80 by default) every weight is
trained briefly, pulled toward the adapted prior's weights by an L2 penalty: on three virtual
units (``iristac bench calibration --prior``, seeds 0-2) no fine-tune left one unit 1.6 deg
behind its own 20-press calibration and 200 steps another 1.9 deg; 80 steps kept all three
within 0.7 deg (docs/calibration.md, "A new unit from a few presses").

The error estimate is honest: leave one press out over the new presses (adapt on the others,
judge the held-out one against its detected circle), the CV report every other model has
(:func:`leave_one_press_out`). The quality gate's minimum of accepted presses
(:data:`calibration.gate.MIN_ACCEPTED`) counts the prior's presses only when the transfer is
measured to work: at least :data:`MIN_NEW_PRESSES` new presses accepted and their
leave-one-out error within :data:`TRANSFER_MARGIN_DEG` of the prior's own cross-validated
error; otherwise the new presses must reach the minimum on their own
(:func:`prior_gate_settings`).

:func:`calibrate_with_prior` is the whole step (``iristac calibrate NEW.h5 --prior CAL.h5``).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from calibration.samples import Samples
from pipeline.base.errors import UserError

__all__ = ["MIN_NEW_PRESSES", "TRANSFER_MARGIN_DEG", "Prior", "load_prior", "adapt_mlp", "leave_one_press_out",
           "prior_gate_settings", "calibrate_with_prior"]

#: Fewest accepted presses of the new unit: leave-one-out then adapts on at least two.
MIN_NEW_PRESSES = 3
#: The prior transfers when the new presses' leave-one-out error is at most the prior's own CV
#: error plus this (degrees); only then do the prior's presses count toward the gate's minimum.
TRANSFER_MARGIN_DEG = 2.0


@dataclass
class Prior:
    """Another unit's calibration, read for adaptation (:func:`load_prior`).

    Attributes
    ----------
    path : str
    model : MLPModel
        Its MLP (``models/mlp``), with its tilt gain and limit.
    meta : dict
        The file's attributes.
    accepted : int
        Presses it was calibrated from (its ``summary.accepted``).
    cv_deg : float or None
        Its MLP's cross-validated mean error (``validation.mlp.cv``).
    """

    path: str
    model: Any
    meta: dict[str, Any]
    accepted: int
    cv_deg: float | None

    @property
    def frame_shape(self) -> tuple[int, ...]:
        """``(P, H, W, C)`` of the frames the prior was calibrated on."""
        return tuple(np.asarray(self.model.reference).shape)


def load_prior(path: str | Path) -> Prior:
    """Read another unit's ``calibration.h5`` and check it has what adaptation needs (an MLP).

    Raises
    ------
    UserError
        No such file, not a calibration, or no MLP (``models/mlp/*``) or no reference frames
        in it (``models/mlp/reference``), each naming the file.
    """
    from calibration.stored import load_calibration

    models, meta = load_calibration(path)
    mlp = models.get("mlp")
    if mlp is None:
        raise UserError(f"{path}: the prior holds no MLP (no models/mlp/* datasets; it has "
                        f"{', '.join(sorted(models)) or 'no model'}); a prior must be calibrated with --model mlp or "
                        "all")
    if getattr(mlp, "reference", None) is None:
        raise UserError(f"{path}: the prior's MLP has no reference frames (models/mlp/reference), so the frame size it "
                        "was calibrated for is unknown; calibrate the prior again")
    summary = meta.get("summary") or {}
    cv = (((meta.get("validation") or {}).get("mlp") or {}).get("cv") or {}).get("cv_mean_angular_error_deg")
    return Prior(str(path), mlp, meta, int(summary.get("accepted") or 0), None if cv is None else float(cv))


def _layout(model) -> dict[str, Any]:
    """Where the MLP's inputs sit: the colour blocks and the position columns."""
    p, h, w, c = np.asarray(model.reference).shape
    m = p * c
    if model.features == "change+reference":
        blocks = {"change": (0, m), "reference": (m, 2 * m)}
    elif model.features == "change":
        blocks = {"change": (0, m)}
    else:
        blocks = {"colour": (0, m)}
    width = sum(b - a for a, b in blocks.values())
    pos = (width, width + 2) if model.position and model.position_degree == 1 else None
    return {"p": p, "c": c, "m": m, "blocks": blocks, "position": pos}


class _Adapter:
    """The affine input map ``x' = T x + s`` with its few free parameters (torch)."""

    def __init__(self, model, n_in: int, position: bool = True):
        import torch

        self.lay = _layout(model)
        if not position:
            self.lay["position"] = None
        self.n_in = n_in
        p, c = self.lay["p"], self.lay["c"]
        self.colour = torch.nn.Parameter(torch.eye(c).repeat(p, 1, 1))
        self.offset = torch.nn.Parameter(torch.zeros(p * c))
        self.pos = torch.nn.Parameter(torch.eye(2))
        self.shift = torch.nn.Parameter(torch.zeros(2))

    def parameters(self) -> list:
        return [self.colour, self.offset] + ([self.pos, self.shift] if self.lay["position"] else [])

    def distance(self):
        """Squared distance of the free parameters from the identity map."""
        import torch

        eye = torch.eye(self.lay["c"])
        d = ((self.colour - eye) ** 2).sum() + (self.offset ** 2).sum()
        if self.lay["position"]:
            d = d + ((self.pos - torch.eye(2)) ** 2).sum() + (self.shift ** 2).sum()
        return d

    def matrices(self):
        """``(T (n_in, n_in), s (n_in,))`` as torch tensors."""
        import torch

        lay = self.lay
        big = torch.block_diag(*self.colour)
        T = torch.eye(self.n_in)
        s = torch.zeros(self.n_in)
        for name, (a, b) in lay["blocks"].items():
            T = _put(T, a, a, big)
            if name in ("reference", "colour"):
                s = torch.cat([s[:a], self.offset, s[b:]])
        if lay["position"]:
            a = lay["position"][0]
            T = _put(T, a, a, self.pos)
            s = torch.cat([s[:a], self.shift, s[a + 2:]])
        return T, s


def _put(T, r: int, c: int, block):
    """``T`` with ``block`` at rows ``r:``, columns ``c:`` (out of place, so gradients flow)."""
    import torch

    n, k = block.shape
    top, mid, bottom = T[:r], T[r:r + n], T[r + n:]
    mid = torch.cat([mid[:, :c], block, mid[:, c + k:]], dim=1)
    return torch.cat([top, mid, bottom], dim=0)


def _training_set(model, samples: Samples, seed: int):
    """Features, targets ``(n_x, n_y)`` and loss weights of the drawn training pixels."""
    x, y, w = model.training_set(samples)
    pick = model.draw(samples, seed)
    return x[pick], y[pick], w[pick] / w[pick].mean()


def adapt_mlp(prior, samples: Samples, reference: np.ndarray | None = None, *, steps: int = 300, lr: float = 0.02,
              map_l2: float = 0.1, position_map: bool = True, finetune_steps: int = 80, finetune_lr: float = 2e-3, finetune_l2: float = 0.1,
              seed: int = 0):
    """The prior's MLP adapted to a new unit's samples: a fitted input map folded into its first layer.

    Parameters
    ----------
    prior : MLPModel
        The other unit's fitted MLP (every member is adapted with one shared map; their mean is
        fitted). Left unchanged.
    samples : Samples
        The new unit's samples (``intensities (N, P, C)``, ``reference (N, P, C)``, ``normals
        (N, 3)``, ``contact (N,)``, ...), with the same ``P`` and ``C`` as the prior's.
    reference : ndarray, shape (P, H, W, C), optional
        The new unit's no-contact reference (kept in the adapted model, as calibrate's is).
    steps : int
        Adam steps fitting the input map (full batch of the prior's ``max_samples`` pixels).
    lr : float
    map_l2 : float
        ``map_l2 x`` the squared distance of the map's parameters from the identity added to the
        loss: few presses, mostly flat pixels, must not carry the map far.
    position_map : bool
        Fit the position part of the map too (False: colours only).
    finetune_steps : int
        Then every weight trained this many steps (0: none; the default, 80, see the module
        docstring) ...
    finetune_lr, finetune_l2 : float
        ... at this learning rate, with ``finetune_l2 x`` the mean squared distance to the
        adapted prior's weights added to the loss.
    seed : int

    Returns
    -------
    MLPModel
        A new model: the adapted nets, the prior's settings, ``tilt_gain`` and ``max_tilt``.
    """
    import copy

    import torch

    from calibration.models.base import seeded_torch
    from calibration.models.mlp import MLPModel

    if not isinstance(prior, MLPModel) or not prior.nets:
        raise UserError(f"adapt_mlp: the prior must be a fitted MLPModel, got {type(prior).__name__}")
    x, y, w = _training_set(prior, samples, seed)
    model = copy.deepcopy(prior)
    with seeded_torch(seed, threads=1):
        xt, yt, wt = torch.from_numpy(x), torch.from_numpy(y), torch.from_numpy(w)[:, None]
        for net in model.nets:
            net.requires_grad_(False)
        ad = _Adapter(prior, x.shape[1], position_map)
        _descend(ad.parameters(), steps, lr, lambda: _loss(model.nets, ad, xt, yt, wt) + map_l2 * ad.distance())
        with torch.no_grad():
            T, s = ad.matrices()
            for net in model.nets:
                first = net[0]
                first.bias.copy_(first.bias + first.weight @ s)
                first.weight.copy_(first.weight @ T)
        if finetune_steps > 0:
            _finetune(model.nets, xt, yt, wt, finetune_steps, finetune_lr, finetune_l2)
        for net in model.nets:
            net.requires_grad_(False)
            net.eval()
    if reference is not None:
        model.reference = np.asarray(reference, np.float32)
        model.shape = tuple(model.reference.shape[1:3])
    model.tilt_gain, model.max_tilt = prior.tilt_gain, prior.max_tilt
    return model


def _weighted_l1(nets, xt, yt, wt):
    """The ensemble's mean ``(n_x, n_y)`` against the targets: weighted L1, as the MLP trains."""
    out = sum(net(xt) for net in nets) / len(nets)
    return (wt * (out - yt).abs()).mean()


def _loss(nets, adapter, xt, yt, wt):
    T, s = adapter.matrices()
    return _weighted_l1(nets, xt @ T.T + s, yt, wt)


def _descend(params, steps: int, lr: float, loss_fn) -> None:
    import torch

    opt = torch.optim.Adam(params, lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(steps, 1))
    for _ in range(steps):
        opt.zero_grad()
        loss = loss_fn()
        loss.backward()
        opt.step()
        sched.step()


def _finetune(nets, xt, yt, wt, steps: int, lr: float, l2: float) -> None:
    start = [[p.detach().clone() for p in net.parameters()] for net in nets]
    params = [p for net in nets for p in net.parameters()]
    for p in params:
        p.requires_grad_(True)

    def loss():
        pull = sum(((p - p0) ** 2).mean() for net, ps in zip(nets, start) for p, p0 in zip(net.parameters(), ps))
        return _weighted_l1(nets, xt, yt, wt) + l2 * pull

    _descend(params, steps, lr, loss)


def leave_one_press_out(prior, samples: Samples, reference: np.ndarray | None = None, *, fold_hook=None,
                        **adapt_options) -> dict[str, Any]:
    """The adaptation's honest error: each new press judged by a model adapted on the others.

    Parameters
    ----------
    prior : MLPModel
    samples : Samples
        The new unit's samples; every accepted press (``press >= 0`` with contact pixels) is
        held out once; the reference pixels (``press = -1``) always train.
    reference : ndarray, optional
    fold_hook : callable, optional
        ``fold_hook(model, [press])`` with each model adapted without ``press``
        (:class:`calibration.ball_gain.OutOfFoldBalls`: its reconstructions of held-out presses).
    **adapt_options
        Passed to :func:`adapt_mlp`.

    Returns
    -------
    dict
        The CV report of :func:`calibration.validate.cv_report` (``cv_mean_angular_error_deg``,
        ``cv_median_angular_error_deg``, ``per_press``, ``folds``, ``invalid_fraction``, ...),
        errors after the prior's tilt gain and limit, plus ``tilt_gain``, ``max_tilt`` and
        ``method: "leave-one-press-out"``.
    """
    from calibration.validate import INVALID_ERROR_DEG, cv_report
    from pipeline.results.evaluate import angular_error_deg

    presses = np.unique(samples.press[(samples.press >= 0) & samples.contact])
    if len(presses) < 2:
        raise UserError(f"leave_one_press_out: needs at least two accepted presses, got {len(presses)}")
    errors = np.full(len(samples), np.nan)
    log = []
    for p in presses:
        model = adapt_mlp(prior, samples.subset(samples.press != p), reference, **adapt_options)
        if fold_hook is not None:
            fold_hook(model, [int(p)])
        test = (samples.press == p) & samples.contact
        n, ok = model.predict(samples.subset(test))
        e = angular_error_deg(n, samples.normals[test])
        errors[test] = np.where(ok & np.isfinite(e), e, INVALID_ERROR_DEG)
        log.append({"test_presses": [int(p)], "train_presses": [int(q) for q in presses if q != p]})
    out = cv_report(errors, samples, log)
    out.update(tilt_gain=prior.tilt_gain, max_tilt=prior.max_tilt, method="leave-one-press-out")
    return out


def prior_gate_settings(prior: Prior, accepted: int, loo_deg: float | None, gate=None):
    """The quality gate's thresholds for an adapted calibration, and whether the prior transfers.

    The prior's presses stand in for missing new ones (the gate's minimum drops to
    :data:`MIN_NEW_PRESSES`) only when the transfer is measured: ``accepted >=
    MIN_NEW_PRESSES`` and the leave-one-out error ``loo_deg`` at most the prior's own CV error
    plus :data:`TRANSFER_MARGIN_DEG`. Otherwise the usual minimum stands.

    Returns
    -------
    (GateSettings, dict)
        The settings, and ``transfers``, ``reason``, ``prior_presses``, ``prior_cv_deg``,
        ``loo_deg``, ``min_accepted`` for the record.

    Examples
    --------
    >>> p = Prior("a.h5", None, {}, 20, 5.0)
    >>> prior_gate_settings(p, 5, 6.2)[0].min_accepted, prior_gate_settings(p, 5, 9.0)[0].min_accepted
    (3, 6)
    >>> prior_gate_settings(p, 2, 4.0)[1]["reason"]
    'only 2 new press(es) accepted: at least 3 measure a transfer'
    >>> prior_gate_settings(p, 5, None)[1]["transfers"]
    False
    """
    from dataclasses import replace

    from calibration.gate import GateSettings

    base = gate or GateSettings()
    limit = None if prior.cv_deg is None else prior.cv_deg + TRANSFER_MARGIN_DEG
    if accepted < MIN_NEW_PRESSES:
        transfers, why = False, f"only {accepted} new press(es) accepted: at least {MIN_NEW_PRESSES} measure a transfer"
    elif limit is None:
        transfers, why = False, f"{prior.path}: no cross-validated MLP error recorded (validation.mlp.cv) to compare with"
    elif loo_deg is None:
        transfers, why = False, "no leave-one-out error of the new presses"
    elif not loo_deg <= limit:
        transfers, why = False, (f"the new presses' leave-one-out error {loo_deg:.2f} deg exceeds the prior's CV "
                                 f"{prior.cv_deg:.2f} + {TRANSFER_MARGIN_DEG:g} deg")
    else:
        transfers, why = True, (f"the new presses' leave-one-out error {loo_deg:.2f} deg is within "
                                f"{TRANSFER_MARGIN_DEG:g} deg of the prior's CV {prior.cv_deg:.2f} deg")
    settings = replace(base, min_accepted=min(base.min_accepted, MIN_NEW_PRESSES)) if transfers else base
    return settings, {"transfers": transfers, "reason": why, "prior_presses": prior.accepted,
                      "prior_cv_deg": prior.cv_deg, "loo_deg": loo_deg, "min_accepted": settings.min_accepted}


def _check_compatible(prior: Prior, found, src: str) -> None:
    """A UserError unless the new frames are the prior's size, patterns and channels and its pixel pitch."""
    want, got = prior.frame_shape, tuple(np.asarray(found.reference).shape)
    if want != got:
        raise UserError(f"{src}: frames are {got[1]} x {got[2]} px with {got[0]} pattern(s) x {got[3]} channel(s), "
                        f"but the prior {prior.path} was calibrated on {want[1]} x {want[2]} px with {want[0]} x "
                        f"{want[3]} (models/mlp/reference); no mapping between the two: import the new unit at the "
                        "prior's size and crop (the same sensor profile)")
    mm = prior.meta.get("mm_per_px")
    if mm and abs(found.mm_per_px / float(mm) - 1.0) > 0.05:
        raise UserError(f"{src}: pixel pitch {found.mm_per_px:.4g} mm/px, but the prior {prior.path} has "
                        f"{float(mm):.4g} (mm_per_px); a unit of the same model at the same size has the same pitch "
                        "within 5 %: check --mm-per-px or the prior")


def calibrate_with_prior(capture, prior: str | Path | Prior, ball_radius_mm: float | None = None,
                         mm_per_px: float | None = None, *, markers=None, detect_options=None, gate=None,
                         seed: int = 0, **adapt_options):
    """Calibrate a new unit from a few presses and another unit's calibration of the same model.

    Parameters
    ----------
    capture : Capture or path
        The new unit's presses (3-5 are enough when the prior transfers), frames ``(K, P, H, W,
        C)`` the size of the prior's.
    prior : path or Prior
        The other unit's ``calibration.h5`` (it needs an MLP).
    ball_radius_mm, mm_per_px : float, optional
        Default: the capture's, then the prior's.
    markers, detect_options
        As :func:`calibration.calibrate.find_circles`; the drift removed is by default the one
        the prior's calibration removed (its ``circle_settings``).
    gate : GateSettings, optional
        Base thresholds; the minimum of accepted presses follows :func:`prior_gate_settings`.
    seed : int
    **adapt_options
        Passed to :func:`adapt_mlp` (``steps``, ``finetune_steps`` ...).

    Returns
    -------
    CalibrationResult
        One model, ``mlp`` (the adapted prior), its ``cv`` the leave-one-press-out report;
        ``meta["prior"]`` records the prior's path, its presses and CV, the adaptation and the
        transfer decision (written to ``calibration.h5`` as the ``prior`` attribute).

    Raises
    ------
    UserError
        A prior without an MLP, of another frame size or pixel pitch; fewer than
        :data:`MIN_NEW_PRESSES` accepted presses (:class:`calibration.gate.CalibrationRefused`).
    """
    from calibration.ball_gain import OutOfFoldBalls
    from calibration.calibrate import CalibrationResult, find_circles
    from calibration.detect import drift_settings, recorded_drift
    from calibration.gate import CalibrationRefused, judge, model_problems
    from pipeline.base.capture import read_capture

    t0 = time.perf_counter()
    pr = prior if isinstance(prior, Prior) else load_prior(prior)
    src = str(capture) if isinstance(capture, (str, Path)) else "capture"
    capture = read_capture(capture) if isinstance(capture, (str, Path)) else capture
    cs = pr.meta.get("circle_settings") or {}
    opts = detect_options or recorded_drift(cs)
    ball = ball_radius_mm or (capture.meta or {}).get("ball_radius_mm") or pr.meta.get("ball_radius_mm")
    mm = mm_per_px or capture.mm_per_px or pr.meta.get("mm_per_px")
    found = find_circles(capture, ball, mm, refine_iterations=0, shrink_px=float(cs.get("shrink_px", 2.0)),
                         markers=markers, strict=False, detect_options=opts, seed=seed)
    _check_compatible(pr, found, src)
    accepted = int(sum(c.accepted for c in found.circles))
    if accepted < MIN_NEW_PRESSES:
        verdict = judge(found.circles, best_model=None, cv_deg=None, ball_radius_error=None,
                        settings=prior_gate_settings(pr, accepted, None, gate)[0])
        raise CalibrationRefused(verdict.message(src) + f" (adapting the prior {pr.path} needs at least "
                                 f"{MIN_NEW_PRESSES} accepted presses)", verdict, found.circles)
    options = {"seed": seed, **adapt_options}
    # The truth-free judge as in calibrate: each held-out press reconstructed by the model adapted
    # without it, and a sphere fitted to it (with the prior's tilt gain, as the model is used).
    balls = OutOfFoldBalls(found.frames, found.reference, [k for k, c in enumerate(found.circles) if c.accepted],
                           found.mm_per_px, float(ball), accepted, markers=found.markers,
                           contacts=[(*c.center_xy, c.radius_px) for c in found.circles])
    cv = leave_one_press_out(pr.model, found.samples, found.reference, fold_hook=balls, **options)
    ball_fit = balls.gain(pr.model.max_tilt)
    cv["ball_gain"] = ball_fit
    model = adapt_mlp(pr.model, found.samples, found.reference, **options)
    settings, transfer = prior_gate_settings(pr, accepted, cv["cv_mean_angular_error_deg"], gate)
    verdict = judge(found.circles, best_model="mlp", cv_deg=cv.get("cv_answered_mean_angular_error_deg"),
                    cv_invalid=cv.get("invalid_fraction"), ball_radius_error=ball_fit["raw_radius_error"],
                    mismatch=found.mismatch, settings=settings)
    verdict.evidence["prior"] = transfer
    seconds = time.perf_counter() - t0
    record = {"path": str(Path(pr.path).resolve()), "key": "models/mlp", "presses": pr.accepted, "cv_deg": pr.cv_deg,
              "adaptation": {"method": "input affine (colour 3x3 + offset per pattern, position 2x2 + shift) folded "
                                       "into the first layer", **_defaults(options)},
              "transfer": transfer}
    fit = {"train_samples": int(len(found.samples)), "members": len(model.nets), "adapted_from": str(pr.path)}
    return CalibrationResult(
        circles=found.circles, models={"mlp": model},
        reports={"mlp": {"fit": fit, "cv": cv, "seconds": seconds, "problems": model_problems(cv, gate)}},
        labels=None, ball_radius_mm=float(ball), mm_per_px=float(found.mm_per_px), shape=tuple(found.reference.shape[1:3]),
        num_patterns=int(found.reference.shape[0]), num_channels=int(found.reference.shape[3]),
        light_rank_ratio=float("nan"), markers=found.markers, verdict=verdict,
        meta={"circle_settings": {"circles": "detected", "refine_model": None, "refine_iterations": 0,
                                  "shrink_px": float(cs.get("shrink_px", 2.0)), "folds": accepted,
                                  **drift_settings(found.options)},
              "reference": found.reference_note, "prior": record, "samples": len(found.samples),
              **({"ball_fit": {"model": "mlp", **ball_fit}} if ball_fit["raw_radius_error"] is not None else {}),
              "contact_samples": int(found.samples.contact.sum())})


def _defaults(options: dict[str, Any]) -> dict[str, Any]:
    """The adaptation's settings as used (:func:`adapt_mlp`'s defaults where not given)."""
    import inspect

    sig = inspect.signature(adapt_mlp)
    out = {k: p.default for k, p in sig.parameters.items() if p.kind == p.KEYWORD_ONLY}
    out.update(options)
    return out
