"""Tactile image formation: illumination model + surface + lighting pattern -> camera frames.

The noiseless core is the image-formation formula of ``docs/design.md`` (the same as :func:`sim.lambertian.shade`)::

    I_pj(x) = mu * sum_i sigma_i W_p[i, j] * rho_j(x) / pi * max(0, n(x) . V_i(x))

Camera and scene effects are composed around it, each computed only when
:class:`RenderSettings` asks for it, in this order:

1. per-LED shading ``s_i = n . V_i`` with ``depth_field`` (V at the displaced surface),
   ``attached_shadows`` (the max), ``specular`` (a Cook-Torrance lobe, :mod:`sim.specular`)
   and ``cast_shadows`` (visibility by marching the height map toward each LED, or along
   each light's direction for far-field lights, :mod:`sim.far_field`);
2. pattern sum, exposure, gains, albedo;
3. ``crosstalk`` (3 x 3 LED colour -> camera channel), ``vignetting``, ``distortion`` (radial
   lens distortion of the camera), ``dark_level``;
4. ``shot_noise`` and ``read_noise`` (seeded), ``saturation`` and ``bit_depth`` quantization.

The per-LED shading depends only on the surface, so :class:`Renderer` computes it once per
surface (:meth:`Renderer.set_surface`) and then renders any number of patterns with one
small matrix product each: that is what makes the virtual camera cheap.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np
import torch

from pipeline.base.frames import optical_to_recon
from sim.geometry.surface import HeightField, flat
from sim.illumination_model import IlluminationModel
from sim.point_source import point_source_field, ring_geometry

__all__ = [
    "RenderSettings",
    "Renderer",
    "render_images",
    "bare_ring_illumination",
    "auto_exposure",
    "EFFECTS",
    "SURFACE_EFFECTS",
    "IMAGE_EFFECTS",
    "load_render_settings",
]

#: Effects that depend on the surface (computed by :meth:`Renderer.set_surface`), in order.
SURFACE_EFFECTS = ("depth_field", "attached_shadows", "specular", "cast_shadows")
#: Effects applied to each rendered image (:meth:`Renderer.render`), in order.
IMAGE_EFFECTS = ("crosstalk", "vignetting", "distortion", "dark_level", "shot_noise", "read_noise", "saturation",
                 "quantization")
#: Every optional effect, in the order it is applied.
EFFECTS = SURFACE_EFFECTS + IMAGE_EFFECTS


@dataclass
class RenderSettings:
    """Camera and scene settings of a rendering, including which effects to compute.

    Attributes
    ----------
    exposure : float
        ``mu``: maps radiance to digital numbers (DN).
    gains : ndarray, shape (L,) or (L, 3), optional
        Per-LED (per-colour) brightness ``sigma_i``.
    attached_shadows : bool
        ``max(0, n . V_i)`` per LED (physical). Off: the linear model.
    specular : float
        Fresnel reflectance ``F0`` at normal incidence of a Cook-Torrance (GGX) specular lobe
        added to the Lambertian term (about 0.04 for plastics); 0 = off (:mod:`sim.specular`).
    roughness : float
        GGX roughness of that lobe, in (0, 1] (small = sharp highlights).
    cast_shadows : bool
        Shadows the surface casts: march the height map toward each LED (or along each
        far-field light's direction).
    cast_shadow_step_px : float
        Marching step (pixels) for cast shadows.
    depth_field : bool
        Evaluate the light field at the displaced surface (needs ``model.V_depth``).
    crosstalk : ndarray, shape (3, 3), optional
        ``C[j, k]``: response of camera channel ``j`` to LED colour ``k`` (identity = none).
    vignetting : float
        Strength ``a`` of ``(1 + a r^2)^-2`` fall-off, ``r`` = radius / half-diagonal; 0 = off.
    distortion : (k1, k2), optional
        Radial lens distortion ``r_d = r (1 + k1 r^2 + k2 r^4)``, ``r`` normalised by the
        half-diagonal.
    dark_level : float
        Offset (DN) added to every pixel; 0 = off.
    shot_noise : float
        Camera gain in DN per electron: shot-noise variance ``shot_noise * signal`` (DN^2),
        Gaussian approximation of Poisson; 0 = off.
    read_noise : float
        Standard deviation (DN) of additive Gaussian read noise; 0 = off.
    saturation : bool
        Clip to ``[0, full scale]`` (``2^bit_depth - 1``, or ``full_scale`` for float output).
    bit_depth : {None, 8, 10, 12, 16}
        Round to integers and return uint8 (8) or uint16; ``None`` returns float32 DN.
    full_scale : float
        Full scale (DN) of float output when ``saturation`` is on and ``bit_depth`` is None.
    seed : int
        Seed of the noise (same seed, same frame).
    """

    exposure: float = 1.0
    gains: Any = None
    attached_shadows: bool = True
    specular: float = 0.0
    roughness: float = 0.3
    cast_shadows: bool = False
    cast_shadow_step_px: float = 1.0
    depth_field: bool = False
    crosstalk: Any = None
    vignetting: float = 0.0
    distortion: Any = None
    dark_level: float = 0.0
    shot_noise: float = 0.0
    read_noise: float = 0.0
    saturation: bool = False
    bit_depth: int | None = None
    full_scale: float = 255.0
    seed: int = 0

    def __post_init__(self):
        if self.bit_depth is not None and self.bit_depth not in (8, 10, 12, 16):
            raise ValueError(f"RenderSettings: bit_depth must be None, 8, 10, 12 or 16, got {self.bit_depth!r}")
        for name in ("exposure", "vignetting", "dark_level", "shot_noise", "read_noise", "full_scale"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.number)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"RenderSettings: {name} must be a finite number >= 0, got {v!r}")
        if not (isinstance(self.specular, (int, float, np.number)) and 0 <= self.specular <= 1):
            raise ValueError(f"RenderSettings: specular (F0) must be in [0, 1], got {self.specular!r}")
        if not (isinstance(self.roughness, (int, float, np.number)) and 0 < self.roughness <= 1):
            raise ValueError(f"RenderSettings: roughness must be in (0, 1], got {self.roughness!r}")
        if not self.cast_shadow_step_px > 0:
            raise ValueError(f"RenderSettings: cast_shadow_step_px must be > 0, got {self.cast_shadow_step_px}")
        if self.crosstalk is not None:
            c = np.asarray(self.crosstalk, dtype=np.float64)
            if c.shape != (3, 3) or not np.all(np.isfinite(c)):
                raise ValueError(f"RenderSettings: crosstalk must be a finite (3, 3) matrix, got shape {c.shape}")
            self.crosstalk = c
        if self.distortion is not None:
            d = np.asarray(self.distortion, dtype=np.float64).reshape(-1)
            if d.shape != (2,) or not np.all(np.isfinite(d)):
                raise ValueError(f"RenderSettings: distortion must be (k1, k2), got {self.distortion!r}")
            self.distortion = d
        if self.gains is not None:
            g = np.asarray(self.gains, dtype=np.float64)
            if g.ndim not in (1, 2) or (g.ndim == 2 and g.shape[1] != 3) or np.any(g < 0):
                raise ValueError(f"RenderSettings: gains must be >= 0 with shape (L,) or (L, 3), got {g.shape}")
            self.gains = g

    @property
    def effects(self) -> tuple[str, ...]:
        """Names of the effects this setting turns on, in :data:`EFFECTS` order.

        Examples
        --------
        >>> RenderSettings(read_noise=2.0, bit_depth=8).effects
        ('attached_shadows', 'read_noise', 'quantization')
        """
        on = {
            "depth_field": self.depth_field,
            "attached_shadows": self.attached_shadows,
            "specular": self.specular > 0,
            "cast_shadows": self.cast_shadows,
            "crosstalk": self.crosstalk is not None,
            "vignetting": self.vignetting > 0,
            "distortion": self.distortion is not None and bool(np.any(self.distortion != 0)),
            "dark_level": self.dark_level > 0,
            "shot_noise": self.shot_noise > 0,
            "read_noise": self.read_noise > 0,
            "saturation": self.saturation,
            "quantization": self.bit_depth is not None,
        }
        return tuple(e for e in EFFECTS if on[e])

    @property
    def max_dn(self) -> float:
        """Largest value a pixel can hold: ``2^bit_depth - 1``, or ``full_scale`` for float output."""
        return float(2 ** self.bit_depth - 1) if self.bit_depth is not None else float(self.full_scale)

    def to_dict(self) -> dict:
        """JSON-able form (arrays as lists), the inverse of ``RenderSettings(**d)``."""
        d = asdict(self)
        return {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in d.items()}


def load_render_settings(path) -> RenderSettings:
    """Read :class:`RenderSettings` from a YAML/JSON file validated by ``data_schemas/configs/render.json``.

    Raises
    ------
    pipeline.base.errors.UserError
        Unreadable file, unknown key or wrong type, naming the file and the key.
    """
    from pipeline.base.modes import read_config_file

    obj = read_config_file("render", path)
    try:
        return RenderSettings(**obj)
    except ValueError as exc:
        from pipeline.base.errors import UserError

        raise UserError(f"{path}: {exc}") from None


# --------------------------------------------------------------------------------------------
# Illumination models

def bare_ring_illumination(shape: tuple[int, int], mm_per_px: float, gel_z: float = 35.0, *, count: int = 24,
                           radius: float = 40.0, m: float = 1.0, cone_half_angle_deg: float = 60.0,
                           depth_heights=None, dtype=np.float32) -> IlluminationModel:
    """Illumination model of a bare LED ring (no lens), in closed form.

    A legitimate near-field model (:func:`sim.point_source.point_source_field`) that stands
    in for the ray tracer's output in tests and examples.

    Parameters
    ----------
    shape : (H, W)
    mm_per_px : float
    gel_z : float
        Optical ``z`` of the gel (mm). With the 40 mm ring and 120 degree LED cones, every LED
        lights a pixel at distance ``rho`` from the axis only if
        ``(40 + rho) / gel_z < tan 60``: the default 35 mm lights a 25 mm wide gel fully.
    count, radius, m, cone_half_angle_deg
        Ring and emitter, as in :func:`sim.point_source.ring_geometry`.
    depth_heights : array_like, shape (D,), optional
        Gel heights (mm toward the camera) at which to sample ``V_depth`` for the
        depth-dependent light field.

    Examples
    --------
    >>> model = bare_ring_illumination((30, 40), 0.5)
    >>> model.V.shape, bool(model.V[..., 2].min() > 0)
    ((24, 30, 40, 3), True)
    """
    pos, axes = ring_geometry(count, radius)
    kw = dict(m=m, cone_half_angle_deg=cone_half_angle_deg, dtype=dtype)
    V = point_source_field(pos, axes, shape, mm_per_px, gel_z, **kw)
    dh = Vd = None
    if depth_heights is not None:
        dh = np.asarray(depth_heights, dtype=np.float64).reshape(-1)
        if dh.size < 2 or np.any(np.diff(dh) <= 0):
            raise ValueError(f"bare_ring_illumination: depth_heights must increase, got {dh.tolist()}")
        Vd = np.stack([point_source_field(pos, axes, shape, mm_per_px, gel_z, gel_height=np.full(shape, z), **kw)
                       for z in dh])
    meta = {"source": "bare_ring", "count": count, "radius": radius, "m": m,
            "cone_half_angle_deg": cone_half_angle_deg}
    return IlluminationModel(V=V, mm_per_px=mm_per_px, led_positions=pos, gel_z=gel_z, depth_heights=dh,
                             V_depth=Vd, meta=meta)


def auto_exposure(model: IlluminationModel, drive, brightness=None, target_dn: float = 200.0,
                  albedo: float = 1.0, gains=None) -> float:
    """Exposure ``mu`` that puts the brightest flat-gel pixel of any pattern at ``target_dn``.

    Examples
    --------
    >>> model = bare_ring_illumination((10, 12), 1.0)
    >>> mu = auto_exposure(model, np.ones((1, 24, 3)), target_dn=100.0)
    >>> s = RenderSettings(exposure=mu)
    >>> round(float(render_images(model, None, np.ones((1, 24, 3)), settings=s).max()), 3)
    100.0
    """
    drive = _check_drive(drive, model.num_leds)
    w = _weights(drive, brightness, 1.0, gains)  # (P, L, 3)
    flat_img = np.einsum("plj,lhw->phwj", w, np.asarray(model.V[..., 2], np.float64)) * albedo / math.pi
    peak = float(flat_img.max())
    if peak <= 0:
        raise ValueError("auto_exposure: the patterns light no pixel of the flat gel")
    return target_dn / peak


# --------------------------------------------------------------------------------------------
# The renderer

def _check_drive(drive, num_leds: int) -> np.ndarray:
    d = np.asarray(drive, dtype=np.float64)
    if d.ndim == 2:
        d = d[None]
    if d.ndim != 3 or d.shape[1:] != (num_leds, 3):
        raise ValueError(f"drive must have shape (P, {num_leds}, 3) or ({num_leds}, 3), got {np.shape(drive)}")
    if not np.all(np.isfinite(d)):
        raise ValueError("drive contains NaN or Inf")
    return d


def _weights(drive, brightness, exposure, gains) -> np.ndarray:
    """``mu * b_p * sigma_i * W_p[i, j]`` as (P, L, 3)."""
    w = drive * exposure
    if brightness is not None:
        b = np.asarray(brightness, dtype=np.float64).reshape(-1)
        if b.shape != (drive.shape[0],):
            raise ValueError(f"brightness must have shape ({drive.shape[0]},), got {np.shape(brightness)}")
        w = w * b[:, None, None]
    if gains is not None:
        g = np.asarray(gains, dtype=np.float64)
        if g.shape[0] != drive.shape[1]:
            raise ValueError(f"gains must have {drive.shape[1]} rows, got shape {g.shape}")
        w = w * (g[None, :, None] if g.ndim == 1 else g[None])
    return w


class Renderer:
    """Renders frames of one illumination model; caches the per-LED shading of a surface.

    Parameters
    ----------
    model : IlluminationModel
    settings : RenderSettings, optional
    device : str or torch.device
        ``'cpu'`` or ``'cuda'``: one code path.
    dtype : torch.dtype
        ``torch.float32`` (default) or ``torch.float64`` for references.

    Attributes
    ----------
    computed : list of str
        The effects actually computed since the last :meth:`set_surface` (tests use it to
        check that a disabled effect costs nothing).

    Examples
    --------
    >>> from sim.geometry import sphere
    >>> model = bare_ring_illumination((24, 32), 0.25)
    >>> r = Renderer(model, RenderSettings(exposure=1e5, read_noise=1.0, bit_depth=8))
    >>> r.set_surface(sphere((24, 32), 0.25, 2.0, 0.5))
    >>> img = r.render(np.ones((24, 3)))
    >>> img.shape, img.dtype.name, r.computed
    ((24, 32, 3), 'uint8', ['attached_shadows', 'read_noise', 'quantization'])
    """

    def __init__(self, model: IlluminationModel, settings: RenderSettings | None = None, device="cpu",
                 dtype=torch.float32):
        if not isinstance(model, IlluminationModel):
            raise TypeError(f"Renderer: model must be an IlluminationModel, got {type(model).__name__}")
        self.model = model
        self.settings = settings or RenderSettings()
        self.device = torch.device(device)
        self.dtype = dtype
        s = self.settings
        if s.gains is not None and s.gains.shape[0] != model.num_leds:
            raise ValueError(f"Renderer: gains must have {model.num_leds} rows, got shape {s.gains.shape}")
        if s.depth_field and model.V_depth is None:
            raise ValueError("Renderer: depth_field needs an IlluminationModel with V_depth (and depth_heights)")
        h, w = model.shape
        # Component planes (3, L, H*W): n . V_i as three multiply-adds, far faster than an einsum.
        V = np.asarray(model.V).reshape(model.num_leds, h * w, 3).transpose(2, 0, 1)
        self._V = torch.as_tensor(np.ascontiguousarray(V), dtype=dtype, device=self.device)
        # Camera effects that do not depend on the scene are prepared once, and only if on.
        self._vignette = self._make_vignette() if s.vignetting > 0 else None
        self._grid = self._make_distortion_grid() if "distortion" in s.effects else None
        self._crosstalk = (torch.as_tensor(s.crosstalk, dtype=dtype, device=self.device)
                           if s.crosstalk is not None else None)
        self._V_depth = None
        self.computed: list[str] = []
        self._surface_effects: list[str] = []
        self.set_surface(None)

    # -- geometry-dependent part ----------------------------------------------------------
    def set_surface(self, surface: HeightField | None, albedo=1.0, *, specular=None, roughness=None) -> None:
        """Compute the per-LED shading ``s_i(x)`` of a surface (``None``: the flat gel).

        Parameters
        ----------
        surface : HeightField or None
        albedo : float or ndarray, shape (H, W) or (H, W, 3)
            Lambertian albedo per camera channel.
        specular, roughness : ndarray, shape (H, W), optional
            Per-pixel materials for the ``specular`` effect (``F0`` in [0, 1], roughness in
            (0, 1]), replacing the settings' single values; only with the effect on.
        """
        h, w = self.model.shape
        if surface is None:
            surface = flat((h, w), self.model.mm_per_px)
        if surface.shape != (h, w):
            raise ValueError(f"Renderer.set_surface: surface has shape {surface.shape}, model has {(h, w)}")
        rho = np.asarray(albedo, dtype=np.float64)
        if rho.ndim == 0:
            rho = np.full((h, w, 3), float(rho))
        elif rho.ndim == 2:
            rho = np.repeat(rho[..., None], 3, axis=-1)
        if rho.shape != (h, w, 3) or not np.all(np.isfinite(rho)) or np.any(rho < 0):
            raise ValueError(f"Renderer.set_surface: albedo must be finite >= 0, scalar, (H, W) or (H, W, 3); "
                             f"got shape {np.shape(albedo)}")
        n = torch.as_tensor(np.ascontiguousarray(surface.normals.reshape(h * w, 3).T), dtype=self.dtype,
                            device=self.device)  # (3, H*W)
        on = self.settings.effects
        done = []
        if "depth_field" in on:
            V = self._depth_field(surface.height)
            done.append("depth_field")
        else:
            V = self._V
        shading = V[0] * n[0] + V[1] * n[1] + V[2] * n[2]  # (L, H*W): n . V_i
        if "attached_shadows" in on:
            shading = shading.clamp_min(0.0)
            done.append("attached_shadows")
        spec = None
        if "specular" in on:
            spec = self._specular_lobe(V, n, specular, roughness)
            done.append("specular")
        elif specular is not None or roughness is not None:
            raise ValueError("Renderer.set_surface: specular/roughness maps need the specular effect "
                             "(RenderSettings.specular > 0)")
        if "cast_shadows" in on:
            vis = self._cast_visibility(surface)
            shading = shading * vis
            spec = None if spec is None else spec * vis
            done.append("cast_shadows")
        self._shading = shading
        self._specular = spec
        self._albedo = torch.as_tensor(rho.reshape(h * w, 3).T, dtype=self.dtype, device=self.device)  # (3, H*W)
        self._surface_effects = done
        self.computed = list(done)

    def _depth_field(self, height: np.ndarray) -> torch.Tensor:
        """V at each pixel's displaced surface point, linear in height between the samples.

        Heights outside the sampled range use the nearest sample (clamped). Returns the
        component planes (3, L, H*W).
        """
        m = self.model
        zs = np.asarray(m.depth_heights, dtype=np.float64)
        hh = np.clip(height.reshape(-1), zs[0], zs[-1])
        k = np.clip(np.searchsorted(zs, hh, side="right") - 1, 0, len(zs) - 2)
        t = (hh - zs[k]) / (zs[k + 1] - zs[k])
        if self._V_depth is None:  # (D, H*W, L, 3) on the device, made on first use
            Vd = np.asarray(m.V_depth).reshape(len(zs), m.num_leds, -1, 3).transpose(0, 2, 1, 3)
            self._V_depth = torch.as_tensor(np.ascontiguousarray(Vd), dtype=self.dtype, device=self.device)
        kt = torch.as_tensor(k, device=self.device)
        tt = torch.as_tensor(t, dtype=self.dtype, device=self.device)[None, :, None]
        px = torch.arange(hh.size, device=self.device)
        lo = self._V_depth[kt, px]  # (H*W, L, 3)
        hi = self._V_depth[kt + 1, px]
        tt = tt.reshape(-1, 1, 1)
        return (lo * (1 - tt) + hi * tt).permute(2, 1, 0)  # (3, L, H*W) component planes

    def _specular_lobe(self, V: torch.Tensor, n: torch.Tensor, specular, roughness) -> torch.Tensor:
        """``f_s max(0, n . V_i)`` (L, H*W) of the Cook-Torrance lobe (:func:`sim.specular.specular_shading`)."""
        from sim.specular import specular_shading

        h, w = self.model.shape
        s = self.settings

        def material(value, default, name, lo_open):
            if value is None:
                return float(default)
            a = np.asarray(value, dtype=np.float64)
            if a.ndim == 0:
                a = np.full((h, w), float(a))
            ok = np.isfinite(a).all() and a.max() <= 1 and (a.min() > 0 if lo_open else a.min() >= 0)
            if a.shape != (h, w) or not ok:
                raise ValueError(f"Renderer.set_surface: {name} must be a scalar or ({h}, {w}) map in "
                                 f"{'(0, 1]' if lo_open else '[0, 1]'}, got shape {a.shape}")
            return torch.as_tensor(a.reshape(-1), dtype=self.dtype, device=self.device)

        return specular_shading(V, n, material(roughness, s.roughness, "roughness", True),
                                material(specular, s.specular, "specular", False))

    def _cast_visibility(self, surface: HeightField) -> torch.Tensor:
        """1 where the segment from the surface point to LED ``i`` clears the height map, else 0.

        Far-field lights (``model.directions``) are traced along their direction by
        :func:`sim.far_field.far_field_visibility`; the rest of this docstring is about LEDs.

        Marches from each surface point toward each LED in steps of ``cast_shadow_step_px``
        and stops once the ray is above the highest point of the map. Outside the image the
        gel is taken as flat (height 0). Returns (L, H*W).
        """
        m = self.model
        if m.directions is not None:
            from sim.far_field import far_field_visibility

            return far_field_visibility(surface.height, m.directions, m.mm_per_px, device=self.device,
                                        dtype=self.dtype)
        h, w = m.shape
        hmax = float(surface.height.max())
        L = m.num_leds
        ones = torch.ones((L, h * w), dtype=self.dtype, device=self.device)
        if hmax <= 0:
            return ones
        px = m.mm_per_px
        # LED positions relative to the gel plane, reconstruction frame (heights toward the camera).
        leds = optical_to_recon(np.asarray(m.led_positions, np.float64))
        leds[:, 2] += m.gel_z
        # pixel -> recon (x, y) in pixel units: x = col - cx, y = -(row - cy)
        cy, cx = (h - 1) / 2, (w - 1) / 2
        dev, dt = self.device, self.dtype
        step = self.settings.cast_shadow_step_px
        # Tolerance against self-occlusion from bilinear interpolation of a curved surface.
        eps = 0.25 * px
        # Only samples higher than hmin + eps can block a ray (rays start at z0 >= hmin and rise), so only
        # pixels near the box around those samples need marching: a large saving for one bump.
        hmin = min(float(surface.height.min()), 0.0)
        tall = np.argwhere(surface.height > hmin + eps)
        vis = ones.clone()
        if len(tall) == 0:
            return vis
        r0, c0 = tall.min(0)
        r1, c1 = tall.max(0)
        hmap = torch.as_tensor(surface.height, dtype=dt, device=dev)[None, None]
        rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        for i in range(L):
            sx, sy, sz = leds[i]
            # Farthest a ray from the gel plane travels horizontally (pixels) before rising above hmax.
            far = math.hypot(sx / px, sy / px) + math.hypot(cx, cy)
            reach = (hmax - hmin) / max(sz - hmax, 1e-9) * far + 1.0
            near = ((rows >= r0 - reach) & (rows <= r1 + reach) & (cols >= c0 - reach) & (cols <= c1 + reach))
            idx = np.flatnonzero(near)
            if idx.size == 0:
                continue
            idx_t = torch.as_tensor(idx, device=dev)
            col = torch.as_tensor(cols.reshape(-1)[idx], dtype=dt, device=dev)
            row = torch.as_tensor(rows.reshape(-1)[idx], dtype=dt, device=dev)
            z0 = hmap.reshape(-1)[idx_t]
            dcol = sx / px - (col - cx)  # pixel-unit offset to the LED, column direction
            drow = -(sy / px) - (row - cy)  # rows grow along -y
            dz = sz - z0
            # Ray parameter at which it rises above hmax; beyond it nothing can occlude.
            t_top = ((hmax - z0) / dz).clamp(0.0, 1.0)
            horiz = torch.sqrt(dcol * dcol + drow * drow)
            n_steps = int(math.ceil(float((t_top * horiz).max()) / step))
            if n_steps == 0:
                continue
            k = torch.arange(1, n_steps + 1, dtype=dt, device=dev) * step
            blocked = torch.zeros(idx.size, dtype=torch.bool, device=dev)
            chunk = max(1, (1 << 21) // n_steps)  # bound the (pixels x steps) temporaries
            for a in range(0, idx.size, chunk):
                sl = slice(a, a + chunk)
                t = k[None, :] / horiz[sl].clamp_min(1e-9)[:, None]  # (N, S)
                valid = t <= t_top[sl, None]
                cs = col[sl, None] + t * dcol[sl, None]
                rs = row[sl, None] + t * drow[sl, None]
                zr = z0[sl, None] + t * dz[sl, None]
                grid = torch.stack([cs / max(w - 1, 1) * 2 - 1, rs / max(h - 1, 1) * 2 - 1], dim=-1)[None]
                hs = torch.nn.functional.grid_sample(hmap, grid, mode="bilinear", padding_mode="zeros",
                                                     align_corners=True)[0, 0]
                blocked[sl] = ((hs > zr + eps) & valid).any(dim=1)
            vis[i, idx_t] = (~blocked).to(dt)
        return vis

    # -- camera effects prepared once -----------------------------------------------------
    def _radius2(self):
        h, w = self.model.shape
        rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
        cy, cx = (h - 1) / 2, (w - 1) / 2
        half_diag = math.hypot(max(cx, 0.5), max(cy, 0.5))
        return rows, cols, cy, cx, half_diag

    def _make_vignette(self) -> torch.Tensor:
        rows, cols, cy, cx, hd = self._radius2()
        r2 = ((rows - cy) ** 2 + (cols - cx) ** 2) / hd ** 2
        v = (1 + self.settings.vignetting * r2) ** -2
        return torch.as_tensor(v.reshape(-1), dtype=self.dtype, device=self.device)

    def _make_distortion_grid(self) -> torch.Tensor:
        """Sampling grid: for each output (distorted) pixel, where it looks on the gel."""
        k1, k2 = self.settings.distortion
        rows, cols, cy, cx, hd = self._radius2()
        xd, yd = (cols - cx) / hd, (rows - cy) / hd
        xu, yu = xd.copy(), yd.copy()
        for _ in range(20):  # fixed point: r_d = r_u (1 + k1 r_u^2 + k2 r_u^4)
            r2 = xu * xu + yu * yu
            f = 1 + k1 * r2 + k2 * r2 * r2
            xu, yu = xd / f, yd / f
        h, w = self.model.shape
        gx = (xu * hd + cx) / max(w - 1, 1) * 2 - 1
        gy = (yu * hd + cy) / max(h - 1, 1) * 2 - 1
        return torch.as_tensor(np.stack([gx, gy], -1)[None], dtype=self.dtype, device=self.device)

    # -- per-frame part -------------------------------------------------------------------
    def render(self, drive, brightness=None, seed: int | None = None) -> np.ndarray:
        """Render the current surface under each pattern.

        Parameters
        ----------
        drive : ndarray, shape (P, L, 3) or (L, 3)
            LED drive ``W_p[i, j]``.
        brightness : ndarray, shape (P,) or float, optional
        seed : int, optional
            Noise seed (default ``settings.seed``).

        Returns
        -------
        ndarray, shape (P, H, W, 3) (or (H, W, 3) for a single (L, 3) drive)
            float32 DN, or uint8 / uint16 when ``bit_depth`` is set.
        """
        single = np.ndim(drive) == 2
        d = _check_drive(drive, self.model.num_leds)
        if brightness is not None and np.ndim(brightness) == 0:
            brightness = np.full(d.shape[0], float(brightness))
        out = self.render_tensor(_weights(d, brightness, self.settings.exposure, self.settings.gains), seed)
        out = out.cpu().numpy()
        if self.settings.bit_depth is not None and self.settings.bit_depth > 8:
            out = out.astype(np.uint16)  # int32 in torch: uint16 arithmetic is not on every device
        out = np.ascontiguousarray(out)
        return out[0] if single else out

    def render_tensor(self, weights: np.ndarray, seed: int | None = None) -> torch.Tensor:
        """Render from full weights ``mu b_p sigma_i W_p[i, j]`` (P, L, 3).

        Returns a (P, H, W, 3) tensor view: float, uint8 (8 bit) or int32 (10-16 bit).
        """
        h, w = self.model.shape
        P = weights.shape[0]
        wt = torch.as_tensor(weights, dtype=self.dtype, device=self.device)
        # (P, 3, L) @ (L, HW) -> (P, 3, HW); the 1/pi of the Lambertian BRDF folded in.
        img = torch.matmul(wt.transpose(1, 2) / math.pi, self._shading) * self._albedo
        if self._specular is not None:  # white highlights: not scaled by the albedo
            img = img + torch.matmul(wt.transpose(1, 2), self._specular)
        done = list(self._surface_effects)
        self._noise_gen = None
        self._noise_seed = self.settings.seed if seed is None else seed
        # Only the effects the settings turn on are called: an effect that is off costs nothing.
        for name in self.settings.effects:
            if name in IMAGE_EFFECTS:
                img = getattr(self, f"_fx_{name}")(img)
                done.append(name)
        self.computed = done
        return img.reshape(P, 3, h, w).permute(0, 2, 3, 1)

    # -- image effects, (P, 3, H*W) -> (P, 3, H*W), in EFFECTS order -------------------------
    def _fx_crosstalk(self, img):
        return torch.einsum("jk,pkx->pjx", self._crosstalk, img)

    def _fx_vignetting(self, img):
        return img * self._vignette

    def _fx_distortion(self, img):
        h, w = self.model.shape
        P = img.shape[0]
        out = torch.nn.functional.grid_sample(img.reshape(P, 3, h, w), self._grid.expand(P, -1, -1, -1),
                                              mode="bilinear", padding_mode="border", align_corners=True)
        return out.reshape(P, 3, h * w)

    def _fx_dark_level(self, img):
        return img + self.settings.dark_level

    def _randn(self, shape):
        if self._noise_gen is None:
            self._noise_gen = torch.Generator(device=self.device)
            self._noise_gen.manual_seed(int(self._noise_seed) & 0x7FFF_FFFF_FFFF_FFFF)
        return torch.randn(shape, generator=self._noise_gen, dtype=self.dtype, device=self.device)

    def _fx_shot_noise(self, img):
        # Gaussian approximation of Poisson: variance = gain (DN/e-) x signal (DN).
        return img + self._randn(img.shape) * torch.sqrt(img.clamp_min(0.0) * self.settings.shot_noise)

    def _fx_read_noise(self, img):
        return img + self.settings.read_noise * self._randn(img.shape)

    def _fx_saturation(self, img):
        return img.clamp(0.0, self.settings.max_dn)

    def _fx_quantization(self, img):
        s = self.settings
        # Rounding plus the representable range: an integer image cannot hold more.
        img = torch.round(img).clamp(0.0, s.max_dn)
        return img.to(torch.uint8 if s.bit_depth == 8 else torch.int32)


def render_images(model: IlluminationModel, surface: HeightField | None, drive, brightness=None, albedo=1.0,
                  settings: RenderSettings | None = None, device="cpu", dtype=torch.float32,
                  seed: int | None = None) -> np.ndarray:
    """Render ``surface`` under each pattern (one-shot form of :class:`Renderer`).

    Parameters
    ----------
    model : IlluminationModel
    surface : HeightField or None
        ``None``: the flat, undeformed gel.
    drive : ndarray, shape (P, L, 3) or (L, 3)
    brightness : ndarray, shape (P,), optional
    albedo : float or ndarray, shape (H, W) or (H, W, 3)
    settings : RenderSettings, optional
    device, dtype
        torch device and float type of the computation.
    seed : int, optional

    Returns
    -------
    ndarray, shape (P, H, W, 3) or (H, W, 3)

    Examples
    --------
    >>> model = bare_ring_illumination((8, 10), 1.0)
    >>> render_images(model, None, np.ones((2, 24, 3))).shape
    (2, 8, 10, 3)
    """
    r = Renderer(model, settings, device=device, dtype=dtype)
    r.set_surface(surface, albedo)
    return r.render(drive, brightness, seed=seed)
