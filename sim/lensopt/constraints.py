"""What a workshop can make: manufacturing constraints on a lens design, as violations in mm.

Every candidate lens is convex by construction (the intersection of the outer half of a
swept arc, a conic top of positive apex radius and a half-space: :mod:`sim.optics.base`), so it
can be turned on a lathe and has no undercut between its faces that a cutter cannot reach.
On top of that :class:`Manufacturing` asks for

``min_thickness``        centre thickness ``apex_z - bottom_z``;
``min_edge_thickness``   height of the side wall, rim (side meets top) above the bottom: no knife edge;
``led_clearance``        distance from each LED's emitting point to the lens surface (the LED
                         package and its solder need room, and the lens must not touch it);
``housing_radius``       the lens's widest radius (it sits inside the sensor's housing, which holds
                         the LED ring and the gel);
``gel_gap``              gap between the apex and the lowest gel height (the gel must not rest on the lens);
``window_radius``        the camera looks at the gel through the lens's top: the top (not the side) must
                         span at least this radius (0: no such limit);
``tolerance``            the lens must still close into a lens with any one dimension off by this much
                         (mm; :func:`sim.lensopt.tolerance.perturbations`): a side arc that only just
                         reaches the top makes a lens that a 0.1 mm error turns into no lens at all.

:func:`violations` returns how far a scene's lens misses each (0 where met). The LED's
distance to the lens is measured in the meridian half-plane through the LED, which is exact
for a solid of revolution (rotating any lens point to the LED's azimuth brings it closer).

Examples
--------
>>> from sim.scene import load_scene
>>> v = violations(load_scene("default-v1"), Manufacturing())
>>> sorted(v), all(x == 0.0 for x in v.values())
(['gel_gap', 'housing_radius', 'led_clearance', 'min_edge_thickness', 'min_thickness', 'tolerance', 'window_radius'], True)
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from sim.scene import Scene

__all__ = ["Manufacturing", "violations", "lens_profile", "led_distance", "closes"]


@dataclass(frozen=True)
class Manufacturing:
    """Limits in mm; ``housing_radius=None`` means the smallest cylinder that holds the LED ring
    (its radius plus 5 mm for the packages and the board) and the gel (the imaging plane's
    half-diagonal)."""

    min_thickness: float = 2.0
    min_edge_thickness: float = 1.0
    led_clearance: float = 0.5
    housing_radius: float | None = None
    gel_gap: float = 1.0
    tolerance: float = 0.1
    window_radius: float = 0.0

    def resolved(self, scene: Scene) -> "Manufacturing":
        """With ``housing_radius`` filled in for ``scene``."""
        if self.housing_radius is not None:
            return self
        w, h = scene.plane.size
        return Manufacturing(self.min_thickness, self.min_edge_thickness, self.led_clearance,
                             max(scene.leds.radius + 5.0, 0.5 * float(np.hypot(w, h))), self.gel_gap,
                             self.tolerance, self.window_radius)

    def as_dict(self) -> dict:
        return asdict(self)


def lens_profile(lens, samples: int = 400) -> np.ndarray:
    """The lens's cross-section in the meridian half-plane ``rho >= 0``: a closed convex polygon
    ``(K, 2)`` of ``(rho, z)`` vertices, counter-clockwise (bottom, side, top).

    Examples
    --------
    >>> from sim.scene import load_scene
    >>> p = lens_profile(load_scene("default-v1").lens, 50)
    >>> p.shape[1], bool(np.isclose(p[:, 1].max(), 16.0))
    (2, True)
    """
    z = np.linspace(lens.bottom_z, lens.rim_z, samples)
    rt = np.linspace(lens.rim_rho, 0.0, samples)
    side = np.stack([lens.side_rho(z), z], axis=1)
    top = np.stack([rt, lens.top_z(rt)], axis=1)
    return np.concatenate([[[0.0, lens.bottom_z]], side, top[1:]], axis=0)


def _inside(profile: np.ndarray, p) -> bool:
    """Point in the convex counter-clockwise polygon (on every edge's left)."""
    a, b = profile, np.roll(profile, -1, axis=0)
    cross = (b[:, 0] - a[:, 0]) * (p[1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (p[0] - a[:, 0])
    return bool(np.all(cross >= -1e-12))


def led_distance(scene: Scene) -> float:
    """Signed distance (mm) from LED 0's emitting point to the lens: negative inside it.

    The ring is symmetric, so LED 0 stands for every LED.
    """
    pos, _ = scene.leds.geometry()
    p = np.array([float(np.hypot(pos[0, 0], pos[0, 1])), float(pos[0, 2])])
    prof = lens_profile(scene.lens)
    a, b = prof, np.roll(prof, -1, axis=0)
    ab = b - a
    t = np.clip(((p - a) * ab).sum(1) / np.maximum((ab * ab).sum(1), 1e-300), 0.0, 1.0)
    dist = float(np.min(np.hypot(*(a + t[:, None] * ab - p).T)))
    return -dist if _inside(prof, p) else dist


def violations(scene: Scene, limits: Manufacturing) -> dict:
    """How far (mm) ``scene``'s lens misses each limit of ``limits`` (0 where it is met)."""
    lim = limits.resolved(scene)
    ln = scene.lens
    widest = float(np.max(ln.side_rho(np.linspace(ln.bottom_z, ln.rim_z, 200)))) if ln.is_arc else ln.cylinder_radius
    gel = scene.plane.z - max(scene.depth_heights)
    return {
        "tolerance": _fragility(scene, lim.tolerance),
        "min_thickness": max(0.0, lim.min_thickness - (ln.apex_z - ln.bottom_z)),
        "min_edge_thickness": max(0.0, lim.min_edge_thickness - (ln.rim_z - ln.bottom_z)),
        "led_clearance": max(0.0, lim.led_clearance - led_distance(scene)),
        "housing_radius": max(0.0, widest - lim.housing_radius),
        "gel_gap": max(0.0, lim.gel_gap - (gel - ln.apex_z)),
        "window_radius": max(0.0, lim.window_radius - ln.rim_rho),
    }


def closes(arc_radius, centre_rho, centre_z, top_radius, apex_z, bottom_z, top_conic=0.0) -> bool:
    """Whether a swept-arc lens with these dimensions closes (the conditions of
    :func:`sim.scene.load_scene`, without building a scene: microseconds, not milliseconds).

    Examples
    --------
    >>> closes(13.5, 28.0, 10.0, 600.0, 16.0, 3.0), closes(13.5, 28.0, 10.0, 600.0, 30.0, 3.0)
    (True, False)
    """
    r1, rc, zc, R, apex, zb, e = arc_radius, centre_rho, centre_z, top_radius, apex_z, bottom_z, 1.0 + top_conic
    if not (zb < apex and abs(zb - zc) < r1 and r1 > 0 and R > 0 and rc >= 0):
        return False

    def h(z):
        w = max(apex - z, 0.0)
        return rc + np.sqrt(max(r1 * r1 - (z - zc) ** 2, 0.0)) - np.sqrt(max(2.0 * R * w - e * w * w, 0.0))

    return bool(h(zb) < 0.0 < h(min(apex, zc + r1)))


def _fragility(scene: Scene, tol: float) -> float:
    """``tol`` times the number of one-dimension +-``tol`` changes that leave no lens (0: robust)."""
    from sim.lensopt.space import design_of
    from sim.lensopt.tolerance import perturbations

    if tol <= 0:
        return 0.0
    base = design_of(scene)
    names = ("arc_radius", "centre_rho", "centre_z", "top_radius", "apex_z", "bottom_z")
    fails = 0
    for k, values in perturbations(scene, names, delta=tol).items():
        for v in values:
            if v is None:
                continue
            d = {**base, k: v}
            if not closes(d["arc_radius"], d["centre_rho"], d["centre_z"], d["top_radius"], d["apex_z"],
                          d["bottom_z"], d["top_conic"]):
                fails += 1
    return tol * fails
