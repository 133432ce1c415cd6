"""Fine surface texture on the indenter, with exact gradients."""

from __future__ import annotations

import math

import numpy as np

from sim.geometry.surface import HeightField, recon_grid

__all__ = ["add_texture"]


def add_texture(field: HeightField, amplitude: float, period: float, angle_deg: float = 0.0,
                kind: str = "grating", seed: int = 0, components: int = 8) -> HeightField:
    """Add a fine texture of peak ``amplitude`` (mm) to the contact region of ``field``.

    The texture belongs to the pressed object, so it only shows where the object touches
    (``field.contact``); outside, the gel stays as it was. Gradients add exactly.

    Parameters
    ----------
    field : HeightField
    amplitude : float
        Peak height of the texture (mm).
    period : float
        Wavelength (mm).
    angle_deg : float
        Direction of the grating's wave vector (``kind='grating'``).
    kind : {'grating', 'random'}
        ``grating``: ``A sin(2 pi k.x / period)``. ``random``: a seeded sum of ``components``
        gratings of that period in random directions and phases, scaled to peak ``A`` bound.
    seed : int
        Seed of the random texture.

    Examples
    --------
    >>> from sim.geometry import sphere
    >>> f = add_texture(sphere((40, 40), 0.05, 2.0, 0.3), amplitude=0.01, period=0.2)
    >>> bool(np.abs(f.p).max() > np.abs(sphere((40, 40), 0.05, 2.0, 0.3).p).max())
    True
    """
    if not (amplitude >= 0 and period > 0):
        raise ValueError(f"add_texture: need amplitude >= 0 and period > 0, got {amplitude}, {period}")
    if kind == "grating":
        angles = np.array([math.radians(angle_deg)])
        phases = np.zeros(1)
        weights = np.ones(1)
    elif kind == "random":
        rng = np.random.default_rng(seed)
        angles = rng.uniform(0, 2 * math.pi, components)
        phases = rng.uniform(0, 2 * math.pi, components)
        weights = np.full(components, 1.0 / components)  # sum of |weights| = 1 keeps |t| <= A
    else:
        raise ValueError(f"add_texture: kind must be 'grating' or 'random', got {kind!r}")
    x, y = recon_grid(field.shape, field.mm_per_px)
    k = 2 * math.pi / period
    t = np.zeros_like(x)
    tx = np.zeros_like(x)
    ty = np.zeros_like(x)
    for a, ph, w in zip(angles, phases, weights):
        kx, ky = k * math.cos(a), k * math.sin(a)
        arg = kx * x + ky * y + ph
        t += w * np.sin(arg)
        tx += w * kx * np.cos(arg)
        ty += w * ky * np.cos(arg)
    m = field.contact
    return HeightField(field.height + amplitude * t * m, field.p + amplitude * tx * m,
                       field.q + amplitude * ty * m, field.contact.copy(), field.mm_per_px)
