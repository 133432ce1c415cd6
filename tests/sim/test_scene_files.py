"""Scene files: shipped scenes load, bad files fail with the file, the field and what was expected."""

import numpy as np
import pytest

from pipeline.base.errors import UserError
from sim.scene import load_scene, scene_from_dict, scene_names, scene_to_dict


def test_shipped_scenes_load_and_round_trip():
    assert {"default", "default-v1", "paper", "paper-optimized", "plano-sphere"} <= set(scene_names())
    new = load_scene("default")
    assert new.leds.tilt_deg == 30.0 and new.design["objective"] == "flux"
    s = load_scene("default-v1")
    assert s.leds.count == 24 and s.leds.radius == 40.0
    assert s.lens.arc_radius == 13.5 and s.lens.top_radius == 600.0
    assert abs(s.lens.refractive_index - 1.49) < 1e-12
    # The rim lies on both the side arc and the top sphere.
    assert abs(float(s.lens.side_rho(s.lens.rim_z)) - s.lens.rim_rho) < 1e-9
    assert abs(float(s.lens.top_z(s.lens.rim_rho)) - s.lens.rim_z) < 1e-6
    again = scene_from_dict(scene_to_dict(s))
    assert again.lens == s.lens and again.effects == s.effects
    p = load_scene("plano-sphere")
    assert p.leds.count == 1 and p.lens.cylinder_radius == 25.0
    assert p.plane.resolution == (300, 300) and p.plane.size == (60.0, 60.0) and p.plane.z == 20.0


def test_scene_path_works(tmp_path):
    import yaml

    f = tmp_path / "mine.yaml"
    d = scene_to_dict(load_scene("default"))
    d["name"] = "mine"
    f.write_text(yaml.safe_dump(d))
    assert load_scene(str(f)).name == "mine"


@pytest.mark.parametrize("change, field, expected", [
    (lambda d: d["leds"].update(count=0), "leds/count", "minimum"),
    (lambda d: d.update(effects=["lens", "sparkles"]), "effects", "sparkles"),
    (lambda d: d["lens"]["side"].update(cylinder_radius=3.0), "lens/side", ""),
    (lambda d: d["lens"]["bottom"].update(z=30.0), "lens/bottom/z", "below"),
    (lambda d: d["imaging_plane"].update(z=10.0), "imaging_plane/z", "above the lens"),
    (lambda d: d["leds"].update(radius=20.0, height=5.0), "leds", "outside the lens"),
    (lambda d: d["leds"].update(rgb=[[1, 1, 1], [1, 0, 0]]), "leds/rgb", "RGB triples"),
])
def test_bad_scene_names_file_and_field(change, field, expected):
    d = scene_to_dict(load_scene("default-v1"))
    change(d)
    with pytest.raises(UserError) as e:
        scene_from_dict(d, source="bad.yaml")
    msg = str(e.value)
    assert "bad.yaml" in msg and field in msg and expected in msg


def test_unknown_scene_and_bad_yaml(tmp_path):
    with pytest.raises(UserError, match="not a shipped scene"):
        load_scene("no-such-scene")
    f = tmp_path / "broken.yaml"
    f.write_text("name: [unclosed\n")
    with pytest.raises(UserError, match="broken.yaml"):
        load_scene(str(f))


def test_effect_switches_and_lens_edits():
    s = load_scene("default-v1")
    assert s.has("lens") and not s.with_effects(remove=["lens"]).has("lens")
    assert s.with_effects(add=["internal_bounces"]).has("internal_bounces")
    with pytest.raises(ValueError):
        s.with_effects(add=["sparkles"])
    t = s.with_lens(arc_radius=12.0)
    assert t.lens.arc_radius == 12.0 and t.lens.rim_z != s.lens.rim_z
    # Dispersion: blue bends more than red (normal dispersion of PMMA).
    nR, nG, nB = s.lens.channel_indices()
    assert nR < nG < nB and abs(nG - 1.49) < 0.01
    assert np.isclose(s.leds.rgb, 1.0).all()
