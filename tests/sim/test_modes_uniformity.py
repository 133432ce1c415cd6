"""Per-channel uniformity of the lighting modes on a flat gel."""

import numpy as np
import pytest

from sim.illumination_model import IlluminationModel
from sim.render import bare_ring_illumination
from sim.uniformity import central_disc, channel_stats, mode_uniformity, uniformity_figure, uniformity_report


@pytest.fixture(scope="module")
def model():
    return bare_ring_illumination((48, 48), 0.4)


def test_constant_field_is_perfectly_uniform():
    V = np.zeros((24, 10, 12, 3), np.float32)
    V[..., 2] = 1.0
    m = IlluminationModel(V=V, mm_per_px=0.5, led_positions=np.zeros((24, 3)), gel_z=30.0)
    rep = mode_uniformity(m, "trichromatic")
    for c in "RGB":
        st = rep["frames"][0]["channels"][c]
        assert st["lit"] and st["cv"] == pytest.approx(0, abs=1e-12) and st["min_over_max"] == pytest.approx(1.0)


def test_channel_stats_by_hand_and_unlit():
    img = np.array([[1.0, 2.0], [3.0, 2.0]])
    st = channel_stats(img)
    assert st["mean"] == 2.0 and st["cv"] == pytest.approx(np.std([1, 2, 3, 2]) / 2)
    assert st["min_over_max"] == pytest.approx(1 / 3) and st["spread"] == 1.0
    assert channel_stats(np.zeros((3, 3)))["lit"] is False
    with pytest.raises(ValueError, match=r"\(3,\)"):
        channel_stats(np.zeros(3))


def test_ring_symmetry_and_the_paper_claim(model):
    rep = uniformity_report(model, ["point", "monochromatic", "trichromatic", "multicolour"])
    # 3-fold symmetric modes on a square image and disc: the three channels agree
    for name in ("trichromatic", "multicolour"):
        cvs = [rep[name]["channels"][c]["cv_mean"] for c in "RGB"]
        assert max(cvs) - min(cvs) < 0.02 * max(cvs)
    # every point-LED frame is the same image rotated by 15 degrees: CVs agree closely
    pcv = [f["channels"]["R"]["cv"] for f in rep["point"]["frames"]]
    assert max(pcv) - min(pcv) < 0.05 * max(pcv)
    # sequential white sectors and one-shot RGB sectors light each channel identically
    for j, c in enumerate("RGB"):
        assert rep["monochromatic"]["frames"][j]["channels"][c]["cv"] == pytest.approx(
            rep["trichromatic"]["frames"][0]["channels"][c]["cv"], rel=1e-9)
    # the paper's point: the colour wheel spreads each channel's source, so channels are more even
    for c in "RGB":
        assert rep["multicolour"]["channels"][c]["cv_mean"] < rep["trichromatic"]["channels"][c]["cv_mean"]
        assert rep["trichromatic"]["channels"][c]["cv_mean"] < rep["point"]["channels"][c]["cv_mean"]


def test_region_and_figure(model, tmp_path):
    region = central_disc(model.shape, 0.5)
    assert region[24, 24] and not region[0, 0]
    small = mode_uniformity(model, "point", region)["channels"]["R"]["cv_mean"]
    full = mode_uniformity(model, "point")["channels"]["R"]["cv_mean"]
    assert small < full
    with pytest.raises(ValueError, match="region"):
        mode_uniformity(model, "point", np.ones((3, 3), bool))
    p = uniformity_figure(model, tmp_path / "u.png", ["trichromatic", "multicolour"])
    import cv2

    img = cv2.imread(str(p))
    assert img is not None and img.shape[0] > 100
