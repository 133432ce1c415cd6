"""Specular reflection: a Cook-Torrance microfacet lobe (GGX) for the renderer's ``specular`` effect.

Real objects are not Lambertian: a glossy surface adds a highlight around the mirror
direction, which breaks least-squares photometric stereo. The renderer adds this term only
when a scene asks for it (``RenderSettings.specular > 0``). For light ``i`` with vector
irradiance ``V_i`` (direction ``l = V_i / |V_i|``), the camera looking along ``v = (0, 0, 1)``
(orthographic, reconstruction frame) and the half vector ``h = (l + v) / |l + v|``::

    radiance_i = (rho / pi + f_s) * max(0, n . V_i)
    f_s = D(n.h) F(v.h) G(n.l, n.v) / (4 (n.l) (n.v))

with the GGX distribution ``D = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2)``, ``a = roughness^2``,
Schlick's Fresnel ``F = F0 + (1 - F0) (1 - v.h)^5`` (``F0`` = ``specular``, the reflectance at
normal incidence: about 0.04 for plastics and paints; ``F0 = 0`` is a matte material, no lobe) and the Smith-Schlick shadowing
``G = G1(n.l) G1(n.v)``, ``G1(x) = x / (x (1 - k) + k)``, ``k = a / 2``. The specular term is
white (dielectric highlights keep the light's colour) and is zero where ``n.l <= 0`` or
``n.v <= 0`` whatever the ``attached_shadows`` setting: a lobe below the horizon has no meaning.
"""

from __future__ import annotations

import math

import torch

__all__ = ["specular_shading", "ggx_brdf"]


def ggx_brdf(n_l: torch.Tensor, n_v: torch.Tensor, n_h: torch.Tensor, v_h: torch.Tensor, roughness,
             f0, sin2_h: torch.Tensor | None = None) -> torch.Tensor:
    """Cook-Torrance GGX BRDF ``f_s`` from the cosines (any broadcastable shapes); 0 where
    ``n.l <= 0`` or ``n.v <= 0``, and where ``f0 == 0`` (a matte material: no lobe, not even
    Schlick's grazing Fresnel term).

    ``sin2_h = |n x h|^2`` may be given: ``D``'s denominator ``sin^2 + a^2 cos^2`` then has no
    cancellation near the peak (``1 - cos^2`` loses float32 digits when ``a`` is small).

    Examples
    --------
    At normal incidence and view, ``f_s = D(1) F0 / 4 = F0 / (4 pi a^2)``:

    >>> one = torch.ones(1, dtype=torch.float64)
    >>> r = 0.5; a = r * r
    >>> round(float(ggx_brdf(one, one, one, one, r, 0.04)[0]), 9) == round(0.04 / (4 * math.pi * a * a), 9)
    True
    """
    a = roughness * roughness
    a2 = a * a
    s2 = (1.0 - n_h * n_h).clamp_min(0.0) if sin2_h is None else sin2_h
    d = s2 + n_h * n_h * a2
    D = a2 / (math.pi * d * d)
    F = f0 + (1.0 - f0) * (1.0 - v_h).clamp(0.0, 1.0) ** 5
    k = a / 2.0
    nl = n_l.clamp_min(0.0)
    nv = n_v.clamp_min(0.0)
    G1l = nl / (nl * (1.0 - k) + k)
    G1v = nv / (nv * (1.0 - k) + k)
    denom = 4.0 * nl * nv
    ok = (n_l > 0) & (n_v > 0) & (torch.as_tensor(f0) > 0)
    f = D * F * G1l * G1v / torch.where(ok, denom, torch.ones_like(denom))
    return torch.where(ok, f, torch.zeros_like(f))


def specular_shading(V: torch.Tensor, n: torch.Tensor, roughness, f0) -> torch.Tensor:
    """``f_s * max(0, n . V_i)`` per light and pixel: ``(L, M)``.

    Parameters
    ----------
    V : tensor, shape (3, L, M)
        Component planes of each light's vector irradiance at each pixel (reconstruction frame).
    n : tensor, shape (3, M)
        Unit normals.
    roughness, f0 : float or tensor of shape (M,)
        GGX roughness (``a = roughness^2``; in (0, 1]) and Fresnel reflectance at normal
        incidence, per pixel (materials) or one value.

    Returns
    -------
    tensor, shape (L, M)
        Added to the Lambertian ``rho / pi * max(0, n . V_i)`` before the pattern sum.

    Examples
    --------
    A mirror-like surface facing the camera, lit from the camera direction, is brightest:

    >>> V = torch.zeros(3, 2, 1, dtype=torch.float64); V[2, 0] = 1.0; V[0, 1] = 0.6; V[2, 1] = 0.8
    >>> n = torch.tensor([[0.0], [0.0], [1.0]], dtype=torch.float64)
    >>> s = specular_shading(V, n, 0.2, 0.04)
    >>> bool(s[0, 0] > 100 * s[1, 0] > 0)
    True
    """
    norm = torch.sqrt(V[0] * V[0] + V[1] * V[1] + V[2] * V[2])  # (L, M) irradiance magnitude
    n_dot_V = V[0] * n[0] + V[1] * n[1] + V[2] * n[2]
    safe = torch.where(norm > 0, norm, torch.ones_like(norm))
    n_l = torch.where(norm > 0, n_dot_V / safe, torch.zeros_like(norm))
    # v = (0, 0, 1): h = (l + v) / |l + v|, with l = V / |V|.
    lz = V[2] / safe
    hx, hy, hz = V[0] / safe, V[1] / safe, lz + 1.0
    hn2 = (hx * hx + hy * hy + hz * hz).clamp_min(torch.finfo(V.dtype).tiny)
    hn = torch.sqrt(hn2)
    n_h = (hx * n[0] + hy * n[1] + hz * n[2]) / hn
    v_h = hz / hn
    cx, cy, cz = n[1] * hz - n[2] * hy, n[2] * hx - n[0] * hz, n[0] * hy - n[1] * hx  # n x h
    sin2 = (cx * cx + cy * cy + cz * cz) / hn2
    n_v = n[2].expand_as(n_l)
    f = ggx_brdf(n_l, n_v, n_h, v_h, roughness, f0, sin2)
    return f * n_dot_V.clamp_min(0.0)
