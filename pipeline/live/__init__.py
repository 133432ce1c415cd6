"""``iristac live``: reconstruct a camera stream as it happens (Python: :func:`run_live`).

Source: a camera (``camera=``: an OpenCV index, URL or video file, or any
:class:`~pipeline.base.camera.Camera`), or the virtual sensor (``virtual=True``: the rendered
gel under the emulated ring, with scripted presses). Lighting: the mode's number of patterns
decides; a single-frame mode (trichromatic, multicolour) reconstructs every frame, a
multi-pattern mode (point, monochromatic) drives the ring through its patterns over serial
(``port=``) or the emulator (``emulate=True``, the C firmware's host build with
``ring_firmware=``) and reconstructs every complete cycle.

- :mod:`pipeline.live.session`: :class:`LiveSession` (set-up: ring, camera, light model,
  solver and integrator from their registries; the loop) and :func:`run_live`;
- :mod:`pipeline.live.sources`: camera frames, ring cycles, scripted presses;
- :mod:`pipeline.live.queue`: :class:`DropQueue`, the drop-oldest queue;
- :mod:`pipeline.live.recorder`: kill-safe recording; :mod:`pipeline.live.view`: the live page;
- :mod:`pipeline.live.virtual`: the virtual sensor's calibration, cached in the store.
"""

from pipeline.live.queue import DropQueue
from pipeline.live.session import DEFAULT_MODE, JSON_KEYS, LiveResult, LiveSession, run_live
from pipeline.live.virtual import virtual_calibration, virtual_calibration_key

__all__ = ["DEFAULT_MODE", "run_live", "LiveSession", "LiveResult", "DropQueue", "JSON_KEYS", "virtual_calibration",
           "virtual_calibration_key"]
