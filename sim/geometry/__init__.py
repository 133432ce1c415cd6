"""Contact geometry: height maps of the pressed gel with exact analytic normals.

Every shape returns a :class:`HeightField` on the camera's pixel grid: heights in mm
(positive toward the camera, :mod:`pipeline.base.frames`), the exact surface gradients ``(p, q)`` in the
reconstruction frame (so normals are analytic, not finite differences) and the contact mask.

>>> from sim.geometry import sphere
>>> f = sphere((40, 60), 0.1, radius=2.0, depth=0.5)
>>> f.height.shape, bool(f.height.max() > 0), f.normals.shape
((40, 60), True, (40, 60, 3))
"""

from sim.geometry.from_file import height_from_file
from sim.geometry.shapes import cone, cylinder, flat_punch, sphere, wedge
from sim.geometry.surface import HeightField, combine, flat, smooth
from sim.geometry.texture import add_texture

__all__ = [
    "HeightField",
    "flat",
    "combine",
    "smooth",
    "sphere",
    "cylinder",
    "flat_punch",
    "cone",
    "wedge",
    "add_texture",
    "height_from_file",
]
