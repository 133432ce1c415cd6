"""The virtual sensor for captures: a rendered gel under the emulated ring's LEDs, with contacts.

:class:`VirtualSensorSpec` describes the sensor (illumination model, the height map of each
contact instance, albedo, noise, bit depth, frame rate); :func:`open_virtual_camera` turns it
into a :class:`ContactCamera`, a :class:`sim.virtual_camera.VirtualCamera` that

- renders whatever the ring emulator shows (read thread-safely from its ground-truth
  history at the start of every exposure, :func:`sim.virtual_camera.ring_led_state`);
- shows the contact the capture plan asks for: the plan calls :meth:`ContactCamera.set_contact`
  with ``k`` before the first pattern of contact instance ``k`` (where a real camera prompts
  the operator to press), and every frame records in ``info["contact"]`` which contact it was
  exposed with, so the plan can prove that no frame is stored under the wrong contact.

:func:`truth_data` gives the ``truth/height``, ``truth/normals`` and ``truth/albedo`` datasets
of the capture (schema ``capture``), from the same :class:`sim.geometry.HeightField` objects the
camera renders.

Examples
--------
>>> from sim.contacts import contact_surfaces
>>> spec = VirtualSensorSpec(contacts=contact_surfaces("sphere", (30, 40), 0.1, 2), shape=(30, 40),
...                          mm_per_px=0.1)
>>> [c.shape for c in spec.surfaces()], spec.model().shape
([(30, 40), (30, 40)], (30, 40))
>>> sorted(truth_data(spec))
['truth/albedo', 'truth/height', 'truth/normals']
"""

from __future__ import annotations

import hashlib
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from pipeline.base.errors import UserError
from sim.contacts import height_field
from sim.geometry import HeightField
from sim.illumination_model import IlluminationModel
from sim.render import RenderSettings, auto_exposure, bare_ring_illumination
from sim.virtual_camera import VirtualCamera, ring_led_state

__all__ = [
    "VirtualSensorSpec",
    "ContactCamera",
    "open_virtual_camera",
    "illumination_option",
    "truth_data",
]

@dataclass
class VirtualSensorSpec:
    """Everything the virtual camera needs: the sensor's light, the contacts, the camera.

    Attributes
    ----------
    illumination : IlluminationModel, optional
        The sensor's illumination (ray-traced ``illumination.h5``, a calibration's model, ...).
        Default: the bare-LED ring in closed form
        (:func:`sim.render.bare_ring_illumination`) at ``shape`` and ``mm_per_px``.
    contacts : sequence of HeightField or ndarray (H, W)
        One surface per contact instance (press), heights in mm toward the camera. Arrays get
        normals by central differences.
    shape : (H, W)
        Image size when ``illumination`` is not given.
    mm_per_px : float
        Pixel pitch when ``illumination`` is not given (else the model's).
    albedo : float or ndarray (H, W) or (H, W, 3)
    settings : RenderSettings, optional
        Full control of the camera effects and exposure ``mu``. Default: attached shadows,
        read noise ``noise_dn``, saturation, ``bit_depth`` quantization and the exposure that
        puts the brightest flat-gel pixel of any pattern at ``target_dn``.
    noise_dn, bit_depth, target_dn
        Used when ``settings`` is omitted. ``bit_depth`` None gives float32 frames.
    fps : float
        Frame rate of the camera clock.
    buffer_size : int
        Frames the camera queues (oldest dropped), like a webcam.
    seed : int
        Seed of the camera noise.
    device : str
        torch device of the renderer.
    """

    illumination: IlluminationModel | None = None
    contacts: Sequence[Any] = ()
    shape: tuple[int, int] = (60, 80)
    mm_per_px: float = 0.1
    albedo: Any = 1.0
    settings: RenderSettings | None = None
    noise_dn: float = 1.0
    bit_depth: int | None = 8
    target_dn: float = 200.0
    fps: float = 60.0
    buffer_size: int = 4
    seed: int = 0
    device: str = "cpu"
    _model: IlluminationModel | None = field(default=None, init=False, repr=False, compare=False)

    def model(self) -> IlluminationModel:
        """The illumination model (built once)."""
        if self._model is None:
            if self.illumination is not None:
                if not isinstance(self.illumination, IlluminationModel):
                    raise UserError(f"virtual camera: illumination must be an IlluminationModel, got "
                                    f"{type(self.illumination).__name__}")
                self._model = self.illumination
            else:
                if len(tuple(self.shape)) != 2 or min(self.shape) < 1 or not self.mm_per_px > 0:
                    raise UserError(f"virtual camera: need an image shape (H, W) >= 1 and mm_per_px > 0, "
                                    f"got {tuple(self.shape)} and {self.mm_per_px}")
                self._model = bare_ring_illumination(tuple(int(s) for s in self.shape), float(self.mm_per_px))
        return self._model

    def surfaces(self) -> list[HeightField]:
        """The contacts as HeightFields on the model's pixel grid (UserError on a shape mismatch)."""
        m = self.model()
        out = []
        for k, c in enumerate(self.contacts):
            if not isinstance(c, HeightField):
                h = np.asarray(c, dtype=np.float64)
                if h.ndim != 2 or not np.all(np.isfinite(h)):
                    raise UserError(f"virtual camera: contacts[{k}] must be a finite height map (H, W) in mm, "
                                    f"got shape {h.shape}")
                c = height_field(h, m.mm_per_px)
            if c.shape != m.shape:
                raise UserError(f"virtual camera: contacts[{k}] has shape {c.shape}, the illumination model "
                                f"has {m.shape}")
            out.append(c)
        return out

    def render_settings(self, drive: np.ndarray, brightness: np.ndarray) -> RenderSettings:
        """``settings``, or the default ones with the exposure fitted to these patterns."""
        if self.settings is not None:
            return self.settings
        try:
            mu = auto_exposure(self.model(), drive, brightness, target_dn=self.target_dn)
            return RenderSettings(exposure=mu, read_noise=float(self.noise_dn), saturation=True,
                                  bit_depth=self.bit_depth, seed=int(self.seed))
        except ValueError as exc:
            raise UserError(f"virtual camera: {exc}") from None

    def fingerprint(self) -> str:
        """A hash of what the frames depend on besides the patterns (contacts, light, albedo),
        so that a resumed capture refuses to mix two different virtual scenes."""
        h = hashlib.sha256()
        m = self.model()
        for a in (m.V, np.asarray(self.albedo, np.float64), *[s.height for s in self.surfaces()]):
            a = np.ascontiguousarray(a)
            h.update(str(a.shape).encode() + a.tobytes())
        h.update(repr((self.noise_dn, self.bit_depth, self.target_dn, self.seed,
                       None if self.settings is None else self.settings.to_dict())).encode())
        return h.hexdigest()


class ContactCamera(VirtualCamera):
    """A :class:`~sim.virtual_camera.VirtualCamera` whose contact is set by the capture plan.

    ``script`` holds one surface per contact instance; :meth:`set_contact` chooses which one
    frames exposed from now on show (None: the flat gel). Frames carry their exposure window
    (``info["exposure_window"]``) and contact (``info["contact"]``, -1 = flat), so the plan
    rejects frames begun before a pattern was confirmed and checks the contact of each frame.
    """

    #: Frames carry their exposure window: no blind settle time is needed.
    reports_exposure = True
    #: Frames carry ``info["contact"]``: the index of the contact instance they show, -1 = none.
    reports_contact = True

    def __init__(self, model, led_state, contacts: Sequence[HeightField] = (), **kw):
        super().__init__(model, led_state, script=[(0.0, c) for c in contacts], **kw)
        self._contact_lock = threading.Lock()
        # (time.monotonic() of the change, contact): the camera clock looks up the contact in
        # force when an exposure *started*, not when its thread got round to it (under load
        # the clock thread can wake after a later set_contact).
        self._contacts: list[tuple[float, int]] = [(-np.inf, -1)]

    def set_contact(self, k: int | None) -> None:
        """Show contact instance ``k`` (None: no contact) in frames whose exposure starts from now."""
        k = -1 if k is None else int(k)
        if not -1 <= k < len(self.script):
            raise ValueError(f"ContactCamera.set_contact: k must be in [-1, {len(self.script)}), got {k}")
        with self._contact_lock:
            self._contacts.append((time.monotonic(), k))

    def contact_at(self, t: float) -> int:
        """The contact shown ``t`` seconds after the camera opened (the start of an exposure)."""
        when = (self._t0 or 0.0) + t
        with self._contact_lock:
            for since, k in reversed(self._contacts):
                if since <= when:
                    return k
        return -1

    @property
    def exposure(self) -> float:
        """The exposure ``mu`` (DN per unit radiance) recorded in the capture."""
        return float(self.settings.exposure)


def open_virtual_camera(spec: VirtualSensorSpec, ring, drive: np.ndarray, brightness: np.ndarray,
                        exposure: float | None = None) -> ContactCamera:
    """Build and open the :class:`ContactCamera` of ``spec`` watching ``ring`` (an emulator).

    Parameters
    ----------
    spec : VirtualSensorSpec
    ring : RingEmulator
        Anything with ``states_during(t0, t1)`` (the LED ground truth).
    drive : ndarray, shape (P, L, 3)
    brightness : ndarray, shape (P,)
        The patterns to be captured (the default exposure is fitted to them).
    exposure : float, optional
        Override the exposure ``mu``.
    """
    model = spec.model()
    drive = np.asarray(drive, np.float64)
    if drive.ndim != 3 or drive.shape[1] != model.num_leds:
        raise UserError(f"virtual camera: the mode drives {drive.shape[1] if drive.ndim == 3 else '?'} LEDs "
                        f"(drive shape {drive.shape}), the illumination model has {model.num_leds}")
    settings = spec.render_settings(drive, brightness)
    try:
        cam = ContactCamera(model, ring_led_state(ring), spec.surfaces(), albedo=spec.albedo, settings=settings,
                            fps=spec.fps, buffer_size=spec.buffer_size, device=spec.device)
        if exposure is not None:
            cam.set_exposure(exposure)
    except ValueError as exc:
        raise UserError(f"virtual camera: {exc}") from None
    cam.open()
    return cam


def truth_data(spec: VirtualSensorSpec) -> dict[str, np.ndarray]:
    """``truth/height`` (K, H, W), ``truth/normals`` (K, H, W, 3), ``truth/albedo`` (H, W, 3), float32.

    The exact surfaces the virtual camera renders (normals in the reconstruction frame).
    """
    m = spec.model()
    h, w = m.shape
    surfaces = spec.surfaces()
    rho = np.asarray(spec.albedo, dtype=np.float32)
    rho = np.broadcast_to(rho[..., None] if rho.ndim == 2 else rho, (h, w, 3)).astype(np.float32)
    return {
        "truth/height": np.stack([s.height for s in surfaces]).astype(np.float32) if surfaces
        else np.zeros((0, h, w), np.float32),
        "truth/normals": np.stack([s.normals for s in surfaces]).astype(np.float32) if surfaces
        else np.zeros((0, h, w, 3), np.float32),
        "truth/albedo": rho,
    }


def illumination_option(path) -> IlluminationModel:
    """The model of ``--illumination FILE``: :func:`sim.synthesize.load_illumination` (schema
    ``illumination``, e.g. written by ``iristac sim synthesize``), errors naming the option.

    Raises
    ------
    UserError
        Missing or invalid file (the store names the file and the problem).
    """
    from pipeline.base.store import StoreError
    from sim.synthesize import load_illumination

    path = Path(path)
    if not path.is_file():
        raise UserError(f"--illumination {path}: no such file")
    try:
        return load_illumination(path)
    except (StoreError, ValueError) as exc:
        raise UserError(f"--illumination {path}: {exc}") from None
