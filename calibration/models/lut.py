"""GelSight-style lookup table: colour change -> surface gradient, for single-RGB-frame modes.

The key of a pixel is its colour change against the reference, ``d = I - I_ref`` (3 values:
one pattern, three channels). The table bins ``d`` on a regular ``bins^3`` grid spanning the
training range, averages the true gradients ``(dh/dx, dh/dy)`` falling in each bin, smooths
sums and counts with a Gaussian (``smooth_bins``), and fills empty bins from the nearest
filled bin within ``fill_radius_bins``; bins beyond that stay invalid (``valid = False``).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from calibration.models.base import CalibrationModel
from calibration.models.nearfield import poly_terms
from calibration.samples import Samples
from pipeline.base.frames import gradients_to_normals, normals_to_gradients

__all__ = ["LookupTable", "LUTModel"]


class LookupTable:
    """Colour-change -> gradient table.

    Attributes
    ----------
    reference : ndarray, shape (H, W, 3)
        The no-contact frame keys are taken against.
    lo, hi : ndarray, shape (3,)
        Range of the colour change covered by the bins.
    table : ndarray, shape (B, B, B, 2)
        Gradient per bin (reconstruction frame, mm/mm).
    filled : ndarray, shape (B, B, B), bool
        Bins with a value (measured or hole-filled).
    """

    def __init__(self, reference: np.ndarray, lo: np.ndarray, hi: np.ndarray, table: np.ndarray, filled: np.ndarray,
                 support: np.ndarray | None = None):
        # support (B, B, B): smoothed count of training samples per bin (None: 1 where filled).
        self.support = np.asarray(filled, np.float32) if support is None else np.asarray(support, np.float32)
        self.reference = np.asarray(reference, dtype=np.float32)
        self.lo = np.asarray(lo, dtype=np.float64)
        self.hi = np.asarray(hi, dtype=np.float64)
        self.table = np.asarray(table, dtype=np.float32)
        self.filled = np.asarray(filled, dtype=bool)
        if self.reference.ndim != 3 or self.reference.shape[-1] != 3:
            raise ValueError(f"LookupTable: reference must be (H, W, 3), got {self.reference.shape}")
        b = self.table.shape[0]
        if self.table.shape != (b, b, b, 2) or self.filled.shape != (b, b, b):
            raise ValueError(f"LookupTable: table (B, B, B, 2) and filled (B, B, B) expected, got {self.table.shape} "
                             f"and {self.filled.shape}")

    @property
    def bins(self) -> int:
        return int(self.table.shape[0])

    def _index(self, diff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        t = (diff - self.lo) / np.maximum(self.hi - self.lo, 1e-9) * self.bins
        idx = np.floor(t).astype(np.int64)
        inside = ((idx >= 0) & (idx < self.bins)).all(axis=-1)
        return np.clip(idx, 0, self.bins - 1), inside

    def lookup(self, images: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients of RGB frames.

        Parameters
        ----------
        images : ndarray, shape (N, H, W, 3), float
            Linear frames (same scale and dark level as the calibration capture).

        Returns
        -------
        gradients : ndarray, shape (N, H, W, 2), float32
            ``(dh/dx, dh/dy)`` in the reconstruction frame; 0 where invalid.
        valid : ndarray, shape (N, H, W), bool
            The colour change fell in a filled bin.
        """
        images = np.asarray(images, dtype=np.float64)
        if images.ndim != 4 or images.shape[1:] != self.reference.shape:
            raise ValueError(f"LookupTable.lookup: images must be (N, {', '.join(map(str, self.reference.shape))}), "
                             f"got {images.shape}")
        return self.lookup_diff(images - self.reference)

    def lookup_diff(self, diff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Gradients ``(..., 2)`` and validity ``(...)`` of colour changes ``diff (..., 3)``."""
        idx, inside = self._index(np.asarray(diff, dtype=np.float64))
        i, j, k = idx[..., 0], idx[..., 1], idx[..., 2]
        valid = inside & self.filled[i, j, k]
        g = np.where(valid[..., None], self.table[i, j, k], 0.0).astype(np.float32)
        return g, valid

    def confidence_diff(self, diff: np.ndarray) -> np.ndarray:
        """``support / (support + 1)`` of the bins of colour changes ``diff (..., 3)``: near 1 in
        well-sampled bins, small in sparsely sampled or hole-filled ones, 0 outside the table."""
        idx, inside = self._index(np.asarray(diff, dtype=np.float64))
        sup = self.support[idx[..., 0], idx[..., 1], idx[..., 2]]
        return np.where(inside & self.filled[idx[..., 0], idx[..., 1], idx[..., 2]], sup / (sup + 1.0), 0.0)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Arrays for calibration.h5 (inverse: :meth:`from_arrays`)."""
        return {"reference": self.reference, "lo": self.lo, "hi": self.hi, "table": self.table,
                "filled": self.filled, "support": self.support}

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "LookupTable":
        return cls(arrays["reference"], arrays["lo"], arrays["hi"], arrays["table"], arrays["filled"],
                   arrays.get("support"))

    @classmethod
    def build(cls, diff: np.ndarray, gradients: np.ndarray, reference: np.ndarray, bins: int = 32,
              smooth_bins: float = 1.0, fill_radius_bins: float = 3.0, range_percentile: float = 0.5
              ) -> tuple["LookupTable", dict[str, Any]]:
        """Build a table from colour changes ``diff (N, 3)`` and gradients ``(N, 2)``.

        Returns the table and a coverage report (``bins_measured``, ``bins_filled``,
        ``samples_in_measured_bins``).

        Examples
        --------
        A colour change that is exactly linear in the gradient is looked up back:

        >>> rng = np.random.default_rng(0)
        >>> g = rng.uniform(-1, 1, (20000, 2)); d = np.c_[g * 40, 20 * g.sum(1)]
        >>> lut, rep = LookupTable.build(d, g, np.zeros((1, 1, 3)), bins=16, smooth_bins=0)
        >>> got, ok = lut.lookup_diff(d[:100])
        >>> bool(ok.all()), float(np.abs(got - g[:100]).max()) < 0.15
        (True, True)
        """
        from scipy import ndimage  # here: a live start loads this module, never fits (docs/live.md)

        diff = np.asarray(diff, dtype=np.float64)
        gradients = np.asarray(gradients, dtype=np.float64)
        if diff.ndim != 2 or diff.shape[1] != 3 or gradients.shape != (len(diff), 2):
            raise ValueError(f"LookupTable.build: diff (N, 3) and gradients (N, 2) expected, got {diff.shape} and "
                             f"{gradients.shape}")
        lo = np.percentile(diff, range_percentile, axis=0)
        hi = np.percentile(diff, 100 - range_percentile, axis=0)
        pad = 0.05 * (hi - lo) + 1e-6
        lut = cls(reference, lo - pad, hi + pad, np.zeros((bins,) * 3 + (2,)), np.zeros((bins,) * 3, bool))
        idx, inside = lut._index(diff)
        flat = np.ravel_multi_index(idx[inside].T, (bins,) * 3)
        count = np.bincount(flat, minlength=bins ** 3).reshape((bins,) * 3).astype(np.float64)
        sums = np.stack([np.bincount(flat, gradients[inside, a], minlength=bins ** 3) for a in range(2)], -1)
        sums = sums.reshape((bins,) * 3 + (2,))
        measured = count > 0
        if smooth_bins > 0:
            count_s = ndimage.gaussian_filter(count, smooth_bins, mode="constant")
            sums = np.stack([ndimage.gaussian_filter(sums[..., a], smooth_bins, mode="constant") for a in range(2)], -1)
        else:
            count_s = count
        has = measured  # smoothing spreads values, but only measured bins count as data
        table = np.where(has[..., None], sums / np.maximum(count_s, 1e-12)[..., None], 0.0)
        dist, nearest = ndimage.distance_transform_edt(~has, return_indices=True)
        filled = dist <= fill_radius_bins
        table = table[nearest[0], nearest[1], nearest[2]] * filled[..., None]
        report = {"bins": bins, "bins_measured": int(has.sum()), "bins_filled": int(filled.sum()),
                  "bins_total": bins ** 3, "samples_in_range": float(inside.mean()),
                  "fill_radius_bins": fill_radius_bins, "smooth_bins": smooth_bins}
        support = np.where(filled, count_s, 0.0)
        return cls(reference, lut.lo, lut.hi, table, filled, support), report


class LUTModel(CalibrationModel):
    """Calibration wrapper of :class:`LookupTable` (needs one pattern with three channels).

    With ``position_degree > 0`` each bin also holds a polynomial in the pixel position
    (:mod:`calibration.models.lut_position`, as Taxim keeps per bin); ``position_ridge`` damps
    its position terms toward the bin's average. Default quadratic with ridge 0.005: on the
    shared real frames (CV on presses 0-19) it takes the LUT from 14.4 to 10.6 deg (linear
    11.0; ridge 0.05: 11.3, 0.001: 11.0, 0: 14.8 — undamped bins seen at one place overfit).
    The plain table (``to_arrays()["table"]``) is what ``iristac reconstruct --solver lut`` reads.
    """

    name = "lut"

    def __init__(self, bins: int = 32, smooth_bins: float = 1.0, fill_radius_bins: float = 3.0,
                 position_degree: int = 2, position_ridge: float = 0.005):
        self.bins, self.smooth_bins, self.fill_radius_bins = bins, smooth_bins, fill_radius_bins
        self.position_degree, self.position_ridge = int(position_degree), float(position_ridge)
        self.table: LookupTable | None = None
        self.position_coef: np.ndarray | None = None  # (B, B, B, T, 2)
        self.coverage: dict[str, Any] = {}

    def fit(self, samples: Samples, reference: np.ndarray | None = None) -> dict[str, Any]:
        from pipeline.base.errors import UserError

        if samples.intensities.shape[1:] != (1, 3):
            raise UserError(f"lut model: needs a single RGB pattern (P = 1, C = 3), the capture has (P, C) = "
                            f"{samples.intensities.shape[1:]}")
        diff = (samples.intensities - samples.reference)[:, 0]
        p, q = normals_to_gradients(samples.normals)
        ref = np.zeros((*samples.shape, 3), np.float32) if reference is None else np.asarray(reference)[0]
        self.table, self.coverage = LookupTable.build(diff, np.stack([p, q], -1), ref, self.bins, self.smooth_bins,
                                                      self.fill_radius_bins)
        if self.position_degree > 0:
            from calibration.models.lut_position import fit_position_coefficients

            idx, inside = self.table._index(diff.astype(np.float64))
            flat = np.ravel_multi_index(idx[inside].T, (self.table.bins,) * 3)
            phi = poly_terms(samples.rows[inside], samples.cols[inside], samples.shape, self.position_degree)
            self.position_coef = fit_position_coefficients(flat, self.table.bins, phi, np.stack([p, q], -1)[inside],
                                                           self.smooth_bins, self.position_ridge)
        rep = self._fit_report(samples)
        rep["coverage"] = self.coverage
        return rep

    confidence_meaning = "support / (support + 1), support the smoothed count of training samples in the pixel's bin"

    def _predict(self, samples: Samples) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        diff = (samples.intensities - samples.reference)[:, 0]
        g, ok = self.table.lookup_diff(diff)
        if self.position_coef is not None:
            from calibration.models.lut_position import evaluate_position_coefficients

            idx, _ = self.table._index(diff.astype(np.float64))
            phi = poly_terms(samples.rows, samples.cols, samples.shape, self.position_degree)
            g = np.where(ok[:, None], evaluate_position_coefficients(self.position_coef, idx, phi), 0.0)
        return gradients_to_normals(g[:, 0], g[:, 1]), ok, self.table.confidence_diff(diff)

    def stored_reference(self) -> np.ndarray | None:
        return None if self.table is None else self.table.reference[None]

    def to_arrays(self) -> dict[str, np.ndarray]:
        out = self.table.to_arrays()
        if self.position_coef is not None:
            out["position_coef"] = self.position_coef.astype(np.float32)
            out["position_degree"] = np.asarray(self.position_degree)
        return out

    @classmethod
    def from_arrays(cls, arrays: dict[str, np.ndarray]) -> "LUTModel":
        """A fitted model from :meth:`to_arrays`' output."""
        model = cls(bins=int(np.asarray(arrays["table"]).shape[0]),
                    position_degree=int(arrays.get("position_degree", 0)))
        model.table = LookupTable.from_arrays(arrays)
        if "position_coef" in arrays:
            model.position_coef = np.asarray(arrays["position_coef"], np.float64)
        return model
