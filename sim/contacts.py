"""Contact objects by name: the one factory behind every virtual press.

(It imports the geometry only when it makes a surface, so that listing :data:`OBJECTS` for
``--help`` or a run config's check stays cheap.)

``iristac capture --object``, a run config's ``capture.object``, ``compare-modes --object``,
the demo's test object and the rendered calibration presses all come from
:func:`contact_surfaces`. The names (:data:`OBJECTS`):

``sphere``, ``cylinder``, ``flat_punch``, ``cone``, ``wedge``
    One shape per contact instance.
``indenters``
    Sphere, cylinder, flat punch, cone and wedge in turn, one per contact instance.
``test-object``
    The demo's test object: a textured ball, a rod and a flat punch pressed at once (the same
    surface for every contact instance).
``none``
    The flat gel.

Anything else is read as a height-map file: ``.npy`` (one map ``(H, W)`` used for every
contact, or a stack ``(K, H, W)``, in mm) or a single-channel ``.png``
(:func:`sim.geometry.from_file.height_from_file`); the map must have the image's shape.

Sizes. With ``size_mm`` given, every contact has that size (the radius; for ``cone`` and
``wedge`` the half angle in degrees) and ``depth_mm``, at a seeded centre uniform in a disc
of ``spread_mm``, clipped so the contact stays inside the image where it can. Without it,
sizes are scaled to the image and vary per contact (seeded): what ``iristac capture
--virtual-camera`` shows when no size is asked for.

Examples
--------
>>> fs = contact_surfaces("sphere", (20, 30), 0.2, 3, size_mm=1.0, depth_mm=0.3, seed=1)
>>> len(fs), fs[0].shape, round(float(fs[0].height.max()), 1)
(3, (20, 30), 0.3)
>>> [bool(f.height.max() > 0) for f in contact_surfaces("indenters", (40, 50), 0.1, 5)]
[True, True, True, True, True]
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

from pipeline.base.errors import UserError

if TYPE_CHECKING:
    import numpy as np

    from sim.geometry.surface import HeightField

__all__ = ["OBJECTS", "contact_surfaces", "test_object", "height_field"]

#: Built-in contact objects (anything else given by name is read as a height-map file).
OBJECTS = ("sphere", "cylinder", "flat_punch", "cone", "wedge", "indenters", "test-object", "none")

_SHAPES = ("sphere", "cylinder", "flat_punch", "cone", "wedge")
_ANGLED = ("cone", "wedge")  # size is a half angle in degrees, not a radius


def contact_surfaces(object: str, shape: tuple[int, int], mm_per_px: float, contacts: int | None = 1, *,
                     size_mm: float | None = None, depth_mm: float = 0.5, spread_mm: float = 3.0,
                     seed: int = 0) -> list[HeightField]:
    """``contacts`` surfaces of the contact object named ``object`` (see the module docstring).

    Parameters
    ----------
    object : str
        A name in :data:`OBJECTS`, or a ``.npy``/``.png`` height-map file.
    shape : (H, W)
    mm_per_px : float
    contacts : int or None
        K, the number of contact instances; None: 1, or the number of maps in a ``.npy`` stack.
    size_mm : float, optional
        The size of every contact (radius in mm; half angle in degrees for ``cone`` and
        ``wedge``). None: sizes scaled to the image, varied per contact.
    depth_mm, spread_mm : float
        Indentation depth, and the radius of the disc the centres are drawn from (with
        ``size_mm`` only).
    seed : int
        Seed of the placement (and of the sizes without ``size_mm``).

    Returns
    -------
    list of HeightField
        K surfaces of shape (H, W), heights in mm toward the camera.

    Raises
    ------
    UserError
        An unknown name, a missing or unreadable file, a map of the wrong shape, or a
        negative count.
    """
    import numpy as np

    if contacts is not None and contacts < 0:
        raise UserError(f"--contacts must be >= 0, got {contacts}")
    h, w = int(shape[0]), int(shape[1])
    if object in OBJECTS:
        count = 1 if contacts is None else int(contacts)
        if object == "none":
            return [height_field(np.zeros((h, w)), mm_per_px) for _ in range(count)]
        if object == "test-object":
            return [test_object((h, w), mm_per_px)] * count
        if size_mm is not None:
            return _sized(object, (h, w), mm_per_px, count, float(size_mm), float(depth_mm), float(spread_mm),
                          seed)
        return _scaled(object, (h, w), mm_per_px, count, seed)
    return _from_file(object, (h, w), mm_per_px, contacts)


def _sized(object, shape, mm_per_px, count, size, depth, spread, seed) -> list[HeightField]:
    """Every contact ``size`` and ``depth`` at seeded centres within ``spread`` of the middle."""
    import numpy as np

    from sim.geometry.shapes import cone, cylinder, flat_punch, sphere, wedge

    h, w = shape
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        which = object if object != "indenters" else _SHAPES[k % len(_SHAPES)]
        angled = which in _ANGLED
        s = (size if object != "indenters" else 60.0) if angled else size
        # Keep the whole contact inside the image where the image is large enough.
        reach = 0.0 if angled else size
        lim = np.maximum(np.array([w, h]) * mm_per_px / 2 - reach, 0.0)
        r, a = spread * np.sqrt(rng.uniform()), rng.uniform(0, 2 * np.pi)
        c = np.clip([r * np.cos(a), r * np.sin(a)], -lim, lim)
        make = {"sphere": sphere, "cylinder": cylinder, "flat_punch": flat_punch, "cone": cone, "wedge": wedge}[which]
        out.append(make(shape, mm_per_px, s, depth, center=(float(c[0]), float(c[1]))))
    return out


def _scaled(object, shape, mm_per_px, count, seed) -> list[HeightField]:
    """Sizes and places scaled to the image and varied per contact (seeded)."""
    import numpy as np

    from sim.geometry.shapes import cone, cylinder, flat_punch, sphere, wedge

    h, w = shape
    # The gel seen by the camera spans (w, h) * mm_per_px; objects are scaled to it so a small
    # test image still shows a whole contact well inside the frame.
    span = min(h, w) * mm_per_px
    rng = np.random.default_rng(seed)
    out = []
    for k in range(count):
        radius = span * rng.uniform(0.25, 0.35)
        depth = radius * rng.uniform(0.2, 0.35)
        center = tuple(rng.uniform(-0.15, 0.15, 2) * span)
        which = object if object != "indenters" else _SHAPES[k % len(_SHAPES)]
        if which == "sphere":
            f = sphere((h, w), mm_per_px, radius, depth, center=center)
        elif which == "cylinder":
            f = cylinder((h, w), mm_per_px, radius, depth, center=center, angle_deg=float(rng.uniform(0, 180)))
        elif which == "flat_punch":
            f = flat_punch((h, w), mm_per_px, 0.6 * radius, depth, center=center, edge_radius=0.2 * radius)
        elif which == "cone":
            f = cone((h, w), mm_per_px, 60.0, depth, center=center)
        else:
            f = wedge((h, w), mm_per_px, 60.0, depth, center=center, angle_deg=float(rng.uniform(0, 180)))
        out.append(f)
    return out


def test_object(shape: tuple[int, int], mm_per_px: float) -> HeightField:
    """The demo's test object: a ball, a cylinder and a flat punch pressed at once, with a fine
    texture on the ball.

    Examples
    --------
    >>> f = test_object((60, 80), 0.3)
    >>> f.height.shape, bool(f.height.max() > 0.3)
    ((60, 80), True)
    """
    from sim.geometry.shapes import cylinder, flat_punch, sphere
    from sim.geometry.surface import combine
    from sim.geometry.texture import add_texture

    h, w = shape
    half_w, half_h = (w - 1) / 2 * mm_per_px, (h - 1) / 2 * mm_per_px
    ball = sphere(shape, mm_per_px, radius=0.22 * min(half_w, half_h) * 2, depth=0.6,
                  center=(-0.45 * half_w, 0.25 * half_h))
    ball = add_texture(ball, amplitude=0.02, period=0.8, angle_deg=30.0)
    rod = cylinder(shape, mm_per_px, radius=1.5, depth=0.4, center=(0.35 * half_w, 0.3 * half_h), angle_deg=60.0)
    punch = flat_punch(shape, mm_per_px, radius=0.2 * min(half_w, half_h), depth=0.3,
                       center=(0.1 * half_w, -0.5 * half_h))
    return combine([ball, rod, punch])


test_object.__test__ = False  # a factory, not a pytest test


def height_field(h: np.ndarray, mm_per_px: float) -> HeightField:
    """A sampled height map ``(H, W)`` in mm as a :class:`HeightField` (normals by central
    differences; contact where the height is above 1 nm)."""
    from pipeline.base.frames import normals_from_height, normals_to_gradients
    from sim.geometry.surface import HeightField

    p, q = normals_to_gradients(normals_from_height(h, mm_per_px))
    return HeightField(h, p, q, h > 1e-9, mm_per_px)


def _from_file(spec: str, shape, mm_per_px, count) -> list[HeightField]:
    import numpy as np

    h, w = shape
    path = Path(spec)
    if path.suffix.lower() not in (".npy", ".png"):
        raise UserError(f"--object {spec!r}: expected one of {', '.join(OBJECTS)} or a .npy/.png height map file")
    if not path.is_file():
        raise UserError(f"--object {path}: height map file not found")
    if path.suffix.lower() == ".png":
        from sim.geometry.from_file import height_from_file

        f = height_from_file(path, mm_per_px)
        if f.shape != (h, w):
            raise UserError(f"--object {path}: expected a height map (H, W) = {(h, w)}, got {f.shape}")
        return [f] * (1 if count is None else int(count))
    try:
        raw = np.load(path, allow_pickle=False)
    except Exception as exc:  # numpy raises several types for bad files
        raise UserError(f"--object {path}: not a readable .npy array ({exc})") from None
    if raw.ndim == 2:
        raw = np.repeat(raw[None], 1 if count is None else count, axis=0)
    if count is None and raw.ndim == 3:
        count = raw.shape[0]
    if raw.ndim != 3 or raw.shape[1:] != (h, w) or raw.shape[0] != count or raw.dtype.kind not in "uif":
        raise UserError(f"--object {path}: expected a real height map (H, W) = {(h, w)} or a stack "
                        f"(K={count}, {h}, {w}) in mm, got {raw.dtype} {raw.shape}")
    if not np.all(np.isfinite(raw)):
        raise UserError(f"--object {path}: height map contains NaN or Inf")
    return [height_field(np.asarray(m, np.float64), mm_per_px) for m in raw]
