"""sim: the optical ray tracer, the tactile image renderer, lighting modes and the virtual sensor.

Coordinate conventions live in :mod:`pipeline.base.frames`. The public entry points (importable
from ``sim``, each loaded on first use: the tracer and renderer load torch and Numba):

- scenes: :func:`load_scene`, :class:`Scene` (``sim/scenes/*.yaml``, :mod:`sim.scene`);
- the ray tracer and the lens: :func:`trace_report` (``iristac sim trace``), :func:`compare_lens`,
  :func:`optimize_lens` (``iristac sim optimize-lens``) (:mod:`sim.lens_design`; the optics
  themselves in :mod:`sim.optics`, the lens designer's parts in :mod:`sim.lensopt`);
- stage 1, synthesize: :func:`load_illumination`, :class:`IlluminationModel` (the stage itself is
  :func:`sim.synthesize.synthesize`, named like its module; :mod:`sim.illumination_model`);
- image formation: :func:`shade` (the noiseless formula, :mod:`sim.lambertian`),
  :class:`Renderer`, :class:`RenderSettings` (:mod:`sim.render`);
- contacts: :data:`OBJECTS`, :func:`contact_surfaces` (:mod:`sim.contacts`; shapes in
  :mod:`sim.geometry`);
- rendered captures: :func:`render_capture`, :func:`sphere_presses` (:mod:`sim.rendered_capture`),
  and the virtual GelSight-type sensor :func:`random_sensor`, :class:`VirtualSensor`
  (:mod:`sim.virtual_sensor`).
"""

from pipeline.base.lazy import lazy_names

_WHERE = {"load_scene": "scene", "Scene": "scene",
          "trace_report": "lens_design", "compare_lens": "lens_design", "optimize_lens": "lens_design",
          "load_illumination": "synthesize", "IlluminationModel": "illumination_model",
          "shade": "lambertian", "Renderer": "render", "RenderSettings": "render",
          "OBJECTS": "contacts", "contact_surfaces": "contacts",
          "render_capture": "rendered_capture", "sphere_presses": "rendered_capture",
          "random_sensor": "virtual_sensor", "VirtualSensor": "virtual_sensor"}
__getattr__, __dir__ = lazy_names(__name__, _WHERE, globals())

__all__ = list(_WHERE)
