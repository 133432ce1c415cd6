"""What every calibration model provides, and the per-pixel solve shared by light-field models.

A model is fitted on :class:`calibration.samples.Samples` and predicts normals for samples,
so that cross-validation treats every model alike. Light-field models (far-field,
near-field, traced) additionally export ``light_field(shape) -> (P, C, H, W, 3)`` such that
``I[p, :, :, c] ~ rho(x) * n(x) . light_field[p, c]`` (reconstruction frame), optionally with
``flat_field (P, C, H, W)`` by which observations are divided first (the far-field model's
albedo from the reference frames; ``None`` means 1).
"""

from __future__ import annotations

import contextlib
from typing import Any

import numpy as np

from calibration.samples import Samples
from pipeline.base.errors import UserError
from pipeline.results.evaluate import angular_error_deg

__all__ = ["net_arrays", "net_state", "ensemble_arrays", "ensemble_states", "seeded_torch", "CalibrationModel", "LightFieldModel", "MIN_FLAT", "flat_field", "solve_normals", "check_light_rank", "fit_tilt_gain",
           "scale_tilt"]

#: A flat field (the no-contact reference over its channel's median level) below this carries no
#: shading to divide by: a printed marker, a corner the vignetting blacks out. Light-field models
#: with a flat field leave such samples out of their fit and give no normal there (invalid).
MIN_FLAT = 0.1


def solve_normals(obs: np.ndarray, lights: np.ndarray, shadow_iterations: int = 2,
                  min_cond: float = 1e-3) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per-pixel least-squares Lambertian photometric stereo, with attached-shadow rejection.

    Parameters
    ----------
    obs : ndarray, shape (N, M)
        Observations (M = pattern-channels).
    lights : ndarray, shape (N, M, 3)
        Light vector of each observation.
    shadow_iterations : int
        After each solve, observations the current normal puts in attached shadow
        (``n . L <= 0``) are dropped and the pixel is solved again (while >= 3 remain).
    min_cond : float
        Pixels whose used light matrix has ``sigma_min / sigma_max`` below this are invalid.

    Returns
    -------
    normals : ndarray, shape (N, 3)
        Unit normals; ``(0, 0, 1)`` where invalid.
    albedo : ndarray, shape (N,)
    valid : ndarray, shape (N,), bool

    Examples
    --------
    >>> L = np.eye(3)[None] * 2.0
    >>> n, rho, ok = solve_normals(np.array([[0.0, 0.6, 0.8]]) * 2.0, L)
    >>> n.round(6).tolist(), rho.round(6).tolist(), ok.tolist()
    ([[0.0, 0.6, 0.8]], [1.0], [True])
    """
    obs = np.asarray(obs, dtype=np.float64)
    lights = np.asarray(lights, dtype=np.float64)
    if obs.ndim != 2 or lights.shape != obs.shape + (3,):
        raise ValueError(f"solve_normals: obs (N, M) and lights (N, M, 3) expected, got {obs.shape} and "
                         f"{lights.shape}")
    use = np.ones(obs.shape, dtype=bool)
    b = np.zeros((len(obs), 3))
    ok = np.zeros(len(obs), dtype=bool)
    for it in range(shadow_iterations + 1):
        Lw = lights * use[..., None]
        Lwt = Lw.transpose(0, 2, 1)  # batched matmuls: BLAS per pixel system, far faster than einsum here
        A = Lwt @ Lw
        rhs = (Lwt @ obs[..., None])[..., 0]
        ev = np.linalg.eigvalsh(A)
        ok = (use.sum(1) >= 3) & (ev[:, 0] > (min_cond ** 2) * np.maximum(ev[:, 2], 1e-30))
        A[~ok] = np.eye(3)
        b = np.where(ok[:, None], np.linalg.solve(A, rhs[..., None])[..., 0], 0.0)
        if it == shadow_iterations:
            break
        lit = (lights @ b[..., None])[..., 0] > 0
        new_use = lit & (lit.sum(1, keepdims=True) >= 3) | ~(lit.sum(1, keepdims=True) >= 3)
        if np.array_equal(new_use, use):
            break
        use = new_use
    rho = np.linalg.norm(b, axis=1)
    ok &= rho > 0
    n = np.where(ok[:, None], b / np.maximum(rho, 1e-30)[:, None], np.array([0.0, 0.0, 1.0]))
    return n, rho, ok


def flat_field(reference, p: int, c: int, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """The reference's flat field and its levels: ``(flat (P * C, H, W) float64, 0 where below
    :data:`MIN_FLAT`; scale (P * C,))``, each pattern-channel over its median level.

    >>> ref = np.full((1, 2, 2, 1), 50.0); ref[0, 0, 0] = 2.0
    >>> flat, scale = flat_field(ref, 1, 1, (2, 2))
    >>> flat[0].tolist(), scale.tolist()
    ([[0.0, 1.0], [1.0, 1.0]], [50.0])
    """
    ref = np.asarray(reference, np.float64).transpose(0, 3, 1, 2).reshape(p * c, *shape)
    scale = np.median(ref.reshape(p * c, -1), axis=1)
    flat = ref / np.maximum(scale[:, None, None], 1e-12)
    # 0 where the reference is dark: no shading there (the solvers of pipeline.normals leave flat <= 0 out).
    return np.where(flat >= MIN_FLAT, flat, 0.0), scale


def check_light_rank(samples: Samples, min_ratio: float = 0.05, what: str = "capture") -> float:
    """Raise :class:`UserError` unless the patterns give three independent light directions.

    Fits the linear far-field model ``I_m = a_m + n . L_m`` to the samples and compares the
    singular values of the stacked ``L (M, 3)``: with fewer than three independent light
    directions (e.g. only LEDs on one diameter of the ring, or fewer than three
    pattern-channels) normals are not determined and no model may be fitted silently.
    A small ratio means degenerate lighting only when the circles' sphere caps explain the
    shading (:func:`calibration.gate.shading_explained`); otherwise the circles (or the
    reference) are at fault and the error says that instead.

    Returns the ratio ``sigma_3 / sigma_1``.
    """
    from calibration.gate import rank_message, shading_explained

    m = samples.flat_observations.shape[1]
    if m < 3:
        raise UserError(f"{what}: {m} pattern-channel(s) give fewer than three light directions; photometric "
                        "calibration needs at least three independent lights")
    ratio, explained = shading_explained(samples)
    if ratio < min_ratio:
        A = np.concatenate([np.ones((len(samples), 1)), samples.normals], axis=1)
        coef = np.linalg.lstsq(A, samples.flat_observations.astype(np.float64), rcond=None)[0]
        raise UserError(rank_message(what, np.linalg.svd(coef[1:].T, compute_uv=False), ratio, min_ratio, explained))
    return ratio


def fit_tilt_gain(predicted_xy: np.ndarray, true_xy: np.ndarray) -> float:
    """The factor that undoes a model's shrinkage toward flat: ``sum |t|^2 / sum p . t``.

    Predictions ``p`` of the tilt ``t = (n_x, n_y)`` from noisy colours are pulled toward the
    flat gel (regression dilution: ``p ~ a t + noise`` with ``a < 1``). Regressing ``p`` on the
    (nearly noise-free) truth estimates ``a``; ``1 / a`` restores the magnitude. Fitted on
    *out-of-fold* predictions of the calibration's own presses (never on a test capture).

    Examples
    --------
    >>> t = np.random.default_rng(0).uniform(-0.6, 0.6, (1000, 2))
    >>> round(fit_tilt_gain(0.9 * t, t), 6)
    1.111111
    """
    p = np.asarray(predicted_xy, np.float64)
    t = np.asarray(true_xy, np.float64)
    den = float(np.sum(p * t))
    return float(np.sum(t * t) / den) if den > 0 else 1.0


def scale_tilt(normals: np.ndarray, gain: float = 1.0, max_tilt: float | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Normals ``(..., 3)`` with ``(n_x, n_y)`` scaled by ``gain`` and clipped to ``|n_xy| <= max_tilt``.

    Returns the new unit normals and a bool array of the clipped ones.

    Examples
    --------
    >>> n, clipped = scale_tilt(np.array([[0.6, 0.0, 0.8], [0.0, 0.0, 1.0]]), 1.5, 0.8)
    >>> n.round(3).tolist(), clipped.tolist()
    ([[0.8, 0.0, 0.6], [0.0, 0.0, 1.0]], [True, False])
    """
    n = np.asarray(normals, np.float64)
    xy = n[..., :2] * gain
    mag = np.hypot(xy[..., 0], xy[..., 1])
    limit = 0.999 if max_tilt is None else min(float(max_tilt), 0.999)
    clipped = mag > limit
    xy = xy * np.where(clipped, limit / np.maximum(mag, 1e-12), 1.0)[..., None]
    return np.concatenate([xy, np.sqrt(np.clip(1.0 - np.sum(xy * xy, -1, keepdims=True), 0.0, 1.0))], -1), clipped


class CalibrationModel:
    """Base class: ``fit(samples) -> report``, ``predict(samples) -> (normals, valid)``.

    Subclasses implement ``_predict(samples) -> (normals, valid, confidence)``; :meth:`predict`
    and :meth:`predict_with_confidence` apply the output correction that calibration sets
    after fitting (:attr:`tilt_gain`, :attr:`max_tilt`), so every caller gets the same normals.
    """

    name = "model"
    #: Scale of the predicted tilt ``(n_x, n_y)`` (:func:`fit_tilt_gain`; 1 until calibrate sets it).
    tilt_gain: float = 1.0
    #: Largest ``|(n_x, n_y)|`` the model may answer (the calibration's truth range); None: no limit.
    max_tilt: float | None = None
    #: Whether calibrate scales this model's tilts by the gain its held-out presses' spheres ask
    #: for (:mod:`calibration.ball_gain`). A family whose gain on presses it never saw is smaller
    #: than that gain's noise and bias sets it False: the gain is still measured and reported, and
    #: the quality gate still judges the uncorrected spheres.
    applies_tilt_gain: bool = True

    def fit(self, samples: Samples) -> dict[str, Any]:  # pragma: no cover - interface
        raise NotImplementedError

    def _predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # pragma: no cover
        raise NotImplementedError

    def to_arrays(self) -> dict[str, np.ndarray]:  # pragma: no cover - interface
        raise NotImplementedError

    #: What :meth:`predict_with_confidence`'s confidence measures (reported in NormalMaps.meta).
    confidence_meaning = "1 where the model gives a normal"

    def predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray]:
        """Unit normals ``(N, 3)`` and validity ``(N,)`` of the samples' pixels."""
        n, ok, _ = self.predict_with_confidence(samples)
        return n, ok

    def predict_with_confidence(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(normals (N, 3), valid (N,), confidence (N,) in [0, 1])``."""
        n, ok, conf = self._predict(samples)
        if self.tilt_gain != 1.0 or self.max_tilt is not None:
            n, _ = scale_tilt(n, self.tilt_gain, self.max_tilt)
        return n, ok, conf

    def output_arrays(self) -> dict[str, np.ndarray]:
        """The output correction for calibration.h5 (``tilt_gain``, ``max_tilt``; read back by
        :func:`calibration.stored.load_calibration`)."""
        out = {"tilt_gain": np.asarray(self.tilt_gain, np.float64)}
        if self.max_tilt is not None:
            out["max_tilt"] = np.asarray(self.max_tilt, np.float64)
        return out

    def stored_reference(self) -> np.ndarray | None:
        """The no-contact frames ``(P, H, W, C)`` the model was calibrated with, if it keeps them."""
        ref = getattr(self, "reference", None)
        return None if ref is None else np.asarray(ref, np.float32)

    def normal_maps(self, frames: np.ndarray, reference: np.ndarray | None = None, *, markers=None):
        """Normals, mask and confidence of whole frames: :func:`calibration.normal_maps.predict_normal_maps`."""
        from calibration.normal_maps import predict_normal_maps

        return predict_normal_maps(self, frames, reference, markers=markers)

    def _fit_report(self, samples: Samples) -> dict[str, Any]:
        n, ok = self.predict(samples.subset(samples.contact))
        err = angular_error_deg(n, samples.normals[samples.contact])[ok]
        return {"train_mean_angular_error_deg": float(err.mean()) if err.size else None,
                "train_samples": int(len(samples)), "train_valid_fraction": float(ok.mean()) if ok.size else 0.0}


class LightFieldModel(CalibrationModel):
    """A model that is a per-pixel light matrix; normals by :func:`solve_normals`."""

    flat: np.ndarray | None = None  # (P, C, H, W) flat field, or None

    def lights_at(self, rows: np.ndarray, cols: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
        """Light vectors ``(N, P * C, 3)`` at the given pixels."""
        raise NotImplementedError  # pragma: no cover - interface

    def light_field(self, shape: tuple[int, int]) -> np.ndarray:
        """Per-pixel light vectors ``(P, C, H, W, 3)`` float32 (the solvers' contract)."""
        h, w = shape
        rows, cols = np.mgrid[:h, :w]
        L = self.lights_at(rows.ravel(), cols.ravel(), shape)  # (HW, M, 3)
        p, c = self.num_patterns, self.num_channels
        return np.ascontiguousarray(L.reshape(h, w, p, c, 3).transpose(2, 3, 0, 1, 4)).astype(np.float32)

    def flat_field(self) -> np.ndarray | None:
        """``(P, C, H, W)`` divisor for observations before the solve, or None."""
        return self.flat

    def _observations(self, samples: Samples) -> np.ndarray:
        obs = samples.flat_observations.astype(np.float64)
        if self.flat is not None:
            f = self.flat.reshape(-1, *samples.shape)[:, samples.rows, samples.cols].T  # (N, M)
            obs = obs / np.maximum(f, 1e-6)
        return obs

    confidence_meaning = "inverse condition number (smallest / largest singular value) of the pixel's light matrix"

    def _predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        L = self.lights_at(samples.rows, samples.cols, samples.shape)
        n, _, ok = solve_normals(self._observations(samples), L)
        if self.flat is not None:  # no shading to read where the reference is dark (MIN_FLAT)
            dark = (self.flat.reshape(-1, *samples.shape)[:, samples.rows, samples.cols] < MIN_FLAT).any(axis=0)
            n = np.where(dark[:, None], np.array([0.0, 0.0, 1.0]), n)
            ok = ok & ~dark
        sv = np.linalg.svd(np.asarray(L, np.float64), compute_uv=False)  # (N, 3)
        return n, ok, np.where(ok, sv[:, -1] / np.maximum(sv[:, 0], 1e-30), 0.0)


def net_arrays(net, prefix: str) -> dict[str, np.ndarray]:
    """A torch network's parameters as calibration.h5 arrays ``<prefix>/<param>`` (the state
    dict's ``.`` written ``_``: ``"0.weight"`` -> ``"0_weight"``); inverse: :func:`net_state`."""
    return {f"{prefix}/{k.replace('.', '_')}": v.detach().cpu().numpy() for k, v in net.state_dict().items()}


def net_state(arrays: dict[str, np.ndarray], prefix: str) -> dict[str, Any]:
    """The state dict :func:`net_arrays` wrote under ``prefix`` (torch tensors, keys with ``.``).

    Raises
    ------
    KeyError
        ``<prefix>/*`` when the arrays hold no parameter under it.
    """
    import torch

    head = prefix + "/"
    state = {k[len(head):].replace("_", ".", 1): torch.from_numpy(np.asarray(v)) for k, v in arrays.items()
             if k.startswith(head)}
    if not state:
        raise KeyError(f"{head}*")
    return state


def ensemble_arrays(nets) -> dict[str, np.ndarray]:
    """An ensemble's parameters as calibration.h5 arrays: ``weights/<param>`` (the first net),
    ``members/<i>/<param>`` (the others); inverse: :func:`ensemble_states`."""
    arrays: dict[str, np.ndarray] = {}
    for i, net in enumerate(nets):
        arrays.update(net_arrays(net, "weights" if i == 0 else f"members/{i}"))
    return arrays


def ensemble_states(arrays: dict[str, np.ndarray], members: int) -> list[dict[str, Any]]:
    """The state dicts of the ``members`` nets :func:`ensemble_arrays` wrote."""
    return [net_state(arrays, "weights" if i == 0 else f"members/{i}") for i in range(int(members))]


@contextlib.contextmanager
def seeded_torch(seed: int, threads: int | None = 1):
    """Torch seeded with ``seed``, deterministic algorithms on and ``threads`` intra-op threads
    (None: torch's setting) for the block; the previous settings are restored after it. Two fits
    of a network in it are bit-identical.

    A net of a calibration's size gains nothing from intra-op threads, and on a loaded 2-core
    machine the spinning workers cost 30x (measured: 150 MLP steps of 2000 samples, 17 s with 2
    threads, 0.5 s with 1).
    """
    import torch

    from pipeline.base.threads import limit_threads

    was = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True, warn_only=True)
    try:
        with limit_threads(torch=int(threads) if threads else None):
            torch.manual_seed(seed)
            yield
    finally:
        torch.use_deterministic_algorithms(was)
