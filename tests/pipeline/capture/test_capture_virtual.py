"""Every shipped lighting mode captured end to end: ring emulator behind a real pty (with
faults), the rendering virtual camera with contacts, truth stored and consistent with the frames."""

from __future__ import annotations

import numpy as np
import pytest

from pipeline.base.errors import UserError
from pipeline.base.frames import normals_to_gradients
from pipeline.base.modes import list_modes, load_mode
from pipeline.base.store import Record, read_record
from pipeline.capture.client import RingDisconnected
from pipeline.capture.plan import journal_path
from pipeline.capture.session import capture
from pipeline.capture.virtual import (
    VirtualSensorSpec,
    illumination_option,
    open_virtual_camera,
    truth_data,
)
from sim.contacts import contact_surfaces
from sim.geometry import HeightField
from sim.render import RenderSettings, render_images

SHAPE = (40, 50)
MM = 0.1


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Small renders spin torch's thread pool on shared cores; one thread is faster here."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


def spec(contacts=2, obj="indenters", **kw) -> VirtualSensorSpec:
    kw.setdefault("fps", 400.0)
    return VirtualSensorSpec(shape=SHAPE, mm_per_px=MM, contacts=contact_surfaces(obj, SHAPE, MM, contacts),
                             **kw)


def rerender(rec: Record, k: int) -> np.ndarray:
    """Contact ``k``'s frames rendered again from the file alone: its truth, drive, brightness
    and render settings (noise off), on the default bare-ring sensor of the same size."""
    d = rec.data
    h = d["truth/height"][k].astype(np.float64)
    p, q = normals_to_gradients(d["truth/normals"][k].astype(np.float64))
    surface = HeightField(h, p, q, h > 0, rec.meta["mm_per_px"])
    settings = RenderSettings(**{**rec.meta["render_settings"], "read_noise": 0.0})
    model = VirtualSensorSpec(shape=SHAPE, mm_per_px=MM).model()
    return render_images(model, surface, d["drive"], d["brightness"], albedo=d["truth/albedo"],
                         settings=settings)


@pytest.mark.parametrize("mode", ["point", "monochromatic", "trichromatic", "multicolour"])
def test_every_mode_end_to_end_with_faults_truth_and_contacts(tmp_path, mode, ring_backend):
    assert mode in list_modes()
    out = tmp_path / "capture.h5"
    s = spec(noise_dn=0.5)
    result = capture(out, mode=mode, emulate=True, faults="drop=0.05,corrupt=0.05", seed=4,
                     virtual_camera=s, timeout=0.01, progress=False, ring_firmware=ring_backend.binary)
    patterns = load_mode(mode)
    n_p = len(patterns.frames)
    assert result.patterns == n_p and result.frames == 1 + n_p + 2 * n_p
    assert result.mislabeled == 0
    rec = read_record(out, schema="capture")
    d, m = rec.data, rec.meta
    assert m["mode"] == mode and m["source"] == "virtual" and m["bit_depth"] == 8
    assert m["pattern_names"] == patterns.pattern_names and m["mm_per_px"] == MM
    assert d["frames"].shape == (2, n_p, *SHAPE, 3) and d["frames"].dtype == np.uint8
    for name, want in truth_data(s).items():
        assert np.array_equal(d[name], want), name
    for k in range(2):
        # Frames agree with a rendering from the stored truth (within the read noise and
        # float32 truth), and the contact shows where the indenter presses.
        again = rerender(rec, k)
        diff = np.abs(d["frames"][k].astype(float) - again)
        assert diff.max() <= 4 and diff.mean() < 0.6, (k, diff.max(), diff.mean())
        press = np.abs(d["frames"][k].astype(float) - d["reference"].astype(float)).max(axis=(0, 3))
        touched = d["truth/height"][k] > 0.05
        assert press[touched].mean() > 10 * max(press[~touched].mean(), 0.5)


def test_disconnect_in_a_press_resumes_that_press_and_refuses_another_scene(tmp_path, ring_backend):
    out = tmp_path / "c.h5"
    s = spec(noise_dn=0.0)
    # dark, 3 references, press 0 pattern 0 done; the ring dies inside press 0.
    with pytest.raises(RingDisconnected, match="rerun the same command to resume"):
        capture(out, mode="monochromatic", emulate=True, faults="disconnect-after=12",
                virtual_camera=s, timeout=0.01, progress=False, ring_firmware=ring_backend.binary)
    assert journal_path(out).exists() and not out.exists()
    with pytest.raises(UserError, match="belongs to a different capture"):
        capture(out, mode="monochromatic", emulate=True, virtual_camera=spec(obj="sphere", noise_dn=0.0),
                timeout=0.01, progress=False, ring_firmware=ring_backend.binary)
    asked = []
    result = capture(out, mode="monochromatic", emulate=True, virtual_camera=s, timeout=0.01,
                     on_contact=asked.append, progress=False, ring_firmware=ring_backend.binary)
    assert 0 < result.resumed_steps < result.frames == 10 and result.mislabeled == 0
    assert asked[0] == 0 and asked == sorted(set(asked))  # the resumed press is set up again
    rec = read_record(out, schema="capture")
    assert rec.meta["runs"] == 2
    for k in range(2):
        assert np.abs(rec.data["frames"][k].astype(float) - rerender(rec, k)).max() <= 1


def test_a_camera_object_on_a_port_with_a_contact_callback(tmp_path, ring_backend):
    """The real-hardware path: a ring on a serial port (an emulator we started, as a lab's ring),
    any Camera object, and a callback told which press comes next (it sets the virtual
    camera's contact, where an operator would press)."""
    s = spec(contacts=2, obj="sphere", noise_dn=0.0, fps=300.0)
    patterns = load_mode("monochromatic")
    pressed = []
    with ring_backend.emulator() as ring:
        cam = open_virtual_camera(s, ring, patterns.drive, patterns.brightness)

        def press(k):
            pressed.append(k)
            cam.set_contact(k)

        with pytest.raises(UserError, match="exactly one of --camera ID and --virtual-camera"):
            capture(tmp_path / "x.h5", mode="monochromatic", port=ring.path, camera=cam,
                    virtual_camera=s)
        result = capture(tmp_path / "c.h5", mode="monochromatic", port=ring.path, camera=cam,
                         contacts=2, on_contact=press, timeout=0.05, progress=False)
    assert pressed == [0, 1] and result.frames == 10
    assert result.mislabeled is None  # no ground truth from a port
    rec = read_record(tmp_path / "c.h5", schema="capture")
    assert rec.meta["source"] == "camera" and "truth/height" not in rec.data
    # Labels checked by the pixels instead: every frame is its own pattern on its own press.
    rec.data.update(truth_data(s))
    rec.meta["render_settings"] = cam.settings.to_dict()
    for k in range(2):
        assert np.abs(rec.data["frames"][k].astype(float) - rerender(rec, k)).max() <= 1


def test_contact_objects_and_illumination_file_errors(tmp_path):
    fs = contact_surfaces("indenters", SHAPE, MM, 5)
    assert len(fs) == 5 and all(f.height.max() > 0 and f.contact.any() for f in fs)
    assert all(f.height.max() == 0 for f in contact_surfaces("none", SHAPE, MM, 2))
    np.save(tmp_path / "one.npy", np.zeros(SHAPE))
    assert len(contact_surfaces(str(tmp_path / "one.npy"), SHAPE, MM, 3)) == 3
    with pytest.raises(UserError, match=r"expected a real height map \(H, W\) = \(10, 10\) or a stack.*got float64 \(1, 40, 50\)"):
        contact_surfaces(str(tmp_path / "one.npy"), (10, 10), MM, None)
    with pytest.raises(UserError, match="expected one of sphere, cylinder, .*indenters, test-object, none or a .npy/.png height map"):
        contact_surfaces("cube", SHAPE, MM, 1)
    with pytest.raises(UserError, match="--illumination .*nope.h5: no such file"):
        illumination_option(tmp_path / "nope.h5")
    (tmp_path / "bad.h5").write_bytes(b"not hdf5")
    with pytest.raises(UserError, match="--illumination .*bad.h5"):
        illumination_option(tmp_path / "bad.h5")
    with pytest.raises(UserError, match="contacts\\[0\\] has shape \\(10, 10\\)"):
        VirtualSensorSpec(shape=SHAPE, mm_per_px=MM, contacts=[np.zeros((10, 10))]).surfaces()


def test_ray_traced_illumination_file_drives_the_virtual_camera(tmp_path):
    """An illumination.h5 from the ray tracer (sim.synthesize, few rays) is what the virtual
    camera renders with, through the CLI's option; its size and pitch become the capture's."""
    from pipeline.capture.session import virtual_sensor
    from sim.synthesize import default_illumination, save_illumination

    model = default_illumination((20, 30), 0.5, rays=10_000)
    path = save_illumination(model, tmp_path / "illumination.h5")
    s = virtual_sensor(obj="sphere", contacts=1, illumination=path, fps=300.0, noise_dn=0.0)
    assert s.model().shape == (20, 30) and np.array_equal(s.model().V, model.V)
    result = capture(tmp_path / "c.h5", mode="trichromatic", emulate=True, virtual_camera=s,
                     timeout=0.01, progress=False)
    rec = read_record(tmp_path / "c.h5", schema="capture")
    assert result.mislabeled == 0 and rec.meta["mm_per_px"] == 0.5
    assert rec.data["frames"].shape == (1, 1, 20, 30, 3) and rec.data["reference"].max() > 0
    assert rec.meta["illumination"]["scene"] == model.meta["scene"]
    with pytest.raises(UserError, match="--mm-per-px 0.1 differs"):
        virtual_sensor(illumination=path, mm_per_px=0.1)


def test_bad_virtual_camera_requests_are_user_errors(tmp_path):
    out = tmp_path / "c.h5"
    with pytest.raises(UserError, match="needs --emulate"):
        capture(out, mode="point", port="/dev/null", virtual_camera=True)
    with pytest.raises(UserError, match="virtual camera:.*exposure must be >= 0, got -1"):
        capture(out, mode="trichromatic", emulate=True, virtual_camera=spec(), exposure=-1.0)
    with pytest.raises(UserError, match="--contacts 3 but the virtual sensor has 2 contacts"):
        capture(out, mode="trichromatic", emulate=True, virtual_camera=spec(), contacts=3)
    with pytest.raises(UserError, match="no such mode|unknown|not found"):
        capture(out, mode="no-such-mode", emulate=True, virtual_camera=spec())
    assert not out.exists()


def test_virtual_capture_on_each_device_matches_the_cpu_float64_rendering(tmp_path, device):
    """One torch code path: the capture's frames on ``device`` equal a float64 CPU rendering."""
    s = spec(contacts=1, obj="sphere", noise_dn=0.0, bit_depth=None, device=device)
    capture(tmp_path / "c.h5", mode="monochromatic", emulate=True, virtual_camera=s, timeout=0.01,
            progress=False)
    rec = read_record(tmp_path / "c.h5", schema="capture")
    import torch

    settings = RenderSettings(**rec.meta["render_settings"])
    want = render_images(s.model(), s.surfaces()[0], rec.data["drive"], rec.data["brightness"],
                         settings=settings, dtype=torch.float64)
    assert np.allclose(rec.data["frames"][0], want, rtol=1e-4, atol=1e-3)


def test_virtual_capture_reconstructs_to_its_truth(tmp_path, ring_backend):
    """Stage 3 -> 4: the near-field solver with the sensor's own illumination recovers the
    stored truth/normals of a captured press (the frames and the truth belong together)."""
    from pipeline.workflows.reconstruct import reconstruct
    from sim.synthesize import save_illumination

    s = spec(contacts=1, obj="sphere", noise_dn=0.5)
    capture(tmp_path / "c.h5", mode="monochromatic", emulate=True, virtual_camera=s, timeout=0.01,
            progress=False, ring_firmware=ring_backend.binary)
    ill = save_illumination(s.model(), tmp_path / "illumination.h5")
    res = reconstruct(tmp_path / "c.h5", illumination=ill, solver="nearfield", out=tmp_path / "out",
                      store=tmp_path / "store", images=False)
    assert res.summary["normal_mean_error_deg"] < 0.5, res.summary
