"""The drift estimator's compiled fit of the constant models against its numpy rounds."""

from __future__ import annotations

import numpy as np
import pytest


@pytest.mark.parametrize("model", ["offset", "gain_offset"])
def test_the_constant_models_compiled_fit_equals_the_numpy_rounds(model):
    """``offset`` and ``gain_offset`` are fitted by one compiled pass (pipeline.normals._drift_kernel):
    the numpy rounds' coefficients, residual and kept pixels, to float64 rounding, a contact trimmed."""
    from pipeline.normals.drift import DriftEstimator

    rng = np.random.default_rng(7)
    ref = rng.uniform(40, 200, (2, 30, 40, 3))
    est = DriftEstimator(ref, model=model, max_samples=900)
    raw = np.clip(np.round(0.85 * ref + 9 + rng.normal(0, 1.5, ref.shape)), 0, 255).astype(np.uint8)
    raw[:, 4:16, 6:20] = 250  # a contact the trimming drops
    y = est.samples(raw)
    fast, slow = est._fit_samples(y), est._fit_numpy(y, est._identity())
    np.testing.assert_allclose(fast.gain, slow.gain, rtol=0, atol=1e-12)
    np.testing.assert_allclose(fast.offset, slow.offset, rtol=0, atol=1e-9)
    assert fast.pixels == slow.pixels and fast.residual_dn == pytest.approx(slow.residual_dn, rel=1e-12)
    if model == "gain_offset":
        assert np.allclose(fast.gain, 0.85, atol=0.01)
