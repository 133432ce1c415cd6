"""Optical scenes as files: load, validate and describe ``sim/scenes/*.yaml``.

A scene is an LED ring, an optional lens (a convex solid of revolution of a refractive
material: a swept-arc or cylindrical side, a spherical top, a plane bottom), the imaging
plane (the gel) and the list of effects the simulator composes. The file is validated
against ``data_schemas/configs/scene.json`` and then geometrically (the lens must close, the
LEDs must sit outside it, the gel above it); every error names the file, the field and what
was expected.

Lengths are millimetres in the optical frame (:mod:`pipeline.base.frames`): origin at the ring centre
on the LED plane, ``+z`` toward the gel.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from pipeline.base.errors import UserError
from sim.point_source import ring_geometry

__all__ = [
    "EFFECTS",
    "LedRing",
    "Lens",
    "ImagingPlane",
    "TraceDefaults",
    "Scene",
    "scene_names",
    "resolve_scene_path",
    "load_scene",
    "scene_from_dict",
]

#: Every effect a scene may ask for (the simulator computes only those listed).
EFFECTS = ("lens", "fresnel", "internal_bounces", "emission_profile", "dispersion", "depth_field")

_SCENES_DIR = Path(__file__).resolve().parent / "scenes"

# Representative wavelengths (nm) of the camera's R, G, B channels, and the Fraunhofer lines
# that define the Abbe number; used only when the scene asks for dispersion.
_CHANNEL_NM = (615.0, 532.0, 465.0)
_NM_D, _NM_F, _NM_C = 587.6, 486.1, 656.3


@dataclass(frozen=True)
class LedRing:
    """A ring of LEDs facing ``+z`` (optionally tilted toward the axis).

    ``rgb`` has shape (L, 3): the RGB emission weights of each LED (``c_ij`` of eq. 15).
    """

    count: int = 24
    radius: float = 40.0
    height: float = 0.0
    tilt_deg: float = 0.0
    phase_deg: float = 0.0
    emission_m: float = 1.0
    cone_half_angle_deg: float = 60.0
    rgb: np.ndarray = field(default_factory=lambda: np.ones((24, 3)))

    def geometry(self) -> tuple[np.ndarray, np.ndarray]:
        """LED positions (L, 3) and unit axes (L, 3), optical frame."""
        return ring_geometry(self.count, self.radius, self.height, self.tilt_deg, self.phase_deg)


@dataclass(frozen=True)
class Lens:
    """A convex lens: the intersection of three convex sets.

    side
        ``rho <= g(z)`` with ``g`` the outer half of a circle of radius ``arc_radius`` centred
        at ``(centre_rho, centre_z)`` in the meridian plane (swept about ``z``: a torus), or
        ``rho <= cylinder_radius``.
    top
        the ball of radius ``top_radius`` whose highest point (apex) is at ``z = apex_z``, or with
        ``top_conic = k != 0`` the solid under the conic of apex radius ``top_radius`` and conic
        constant ``k`` (:mod:`sim.optics.conic`).
    bottom
        the half-space ``z >= bottom_z``.

    ``rim_z``/``rim_rho`` (where side meets top) and ``bottom_rho`` are derived on load.
    """

    refractive_index: float
    top_radius: float
    apex_z: float
    bottom_z: float
    arc_radius: float | None = None
    centre_rho: float | None = None
    centre_z: float | None = None
    cylinder_radius: float | None = None
    abbe_number: float | None = None
    top_aperture: float | None = None
    bottom_aperture: float | None = None
    top_conic: float = 0.0
    rim_z: float = float("nan")
    rim_rho: float = float("nan")
    bottom_rho: float = float("nan")

    @property
    def is_arc(self) -> bool:
        return self.arc_radius is not None

    def side_rho(self, z):
        """Side radius ``g(z)`` on ``[bottom_z, rim_z]`` (numpy, for drawing and checks)."""
        z = np.asarray(z, dtype=float)
        if not self.is_arc:
            return np.full_like(z, self.cylinder_radius)
        return self.centre_rho + np.sqrt(np.clip(self.arc_radius ** 2 - (z - self.centre_z) ** 2, 0.0, None))

    def top_z(self, rho):
        """Height of the top surface (sphere or conic) at radius ``rho`` (numpy)."""
        rho = np.asarray(rho, dtype=float)
        if self.top_conic == 0.0:
            return self.apex_z - self.top_radius + np.sqrt(np.clip(self.top_radius ** 2 - rho ** 2, 0.0, None))
        e, R = 1.0 + self.top_conic, self.top_radius
        # The conic's sag (sim.optics.conic.conic_sag); past an ellipsoid's equator it has no
        # value, so rho is clamped to the equator.
        r = np.minimum(rho, R / np.sqrt(e)) if e > 0 else rho
        return self.apex_z - r * r / (R * (1.0 + np.sqrt(np.clip(1.0 - e * r * r / (R * R), 0.0, None))))

    def top_rho(self, z):
        """Radius of the top surface at height ``z`` (numpy; 0 above the apex)."""
        w = np.clip(self.apex_z - np.asarray(z, dtype=float), 0.0, None)
        return np.sqrt(np.clip(2.0 * self.top_radius * w - (1.0 + self.top_conic) * w * w, 0.0, None))

    def channel_indices(self) -> tuple[float, float, float]:
        """Refractive index at the R, G, B channel wavelengths (Cauchy fit to n_d and V_d)."""
        nd = self.refractive_index
        if self.abbe_number is None:
            return (nd, nd, nd)
        dn = (nd - 1.0) / self.abbe_number  # n_F - n_C
        b = dn / (1.0 / _NM_F ** 2 - 1.0 / _NM_C ** 2)
        a = nd - b / _NM_D ** 2
        return tuple(float(a + b / lam ** 2) for lam in _CHANNEL_NM)


@dataclass(frozen=True)
class ImagingPlane:
    """The gel: a rectangle at ``z`` of ``size = (width_x, height_y)`` mm, ``resolution = (rows, cols)``."""

    z: float
    size: tuple[float, float]
    resolution: tuple[int, int]

    @property
    def mm_per_px(self) -> tuple[float, float]:
        """Pixel pitch ``(along y / rows, along x / cols)``."""
        return self.size[1] / self.resolution[0], self.size[0] / self.resolution[1]


@dataclass(frozen=True)
class TraceDefaults:
    rays: int = 1_000_000
    sampler: str = "grid"
    seed: int = 0
    intersection: str = "robust"
    newton_iterations: int = 20


@dataclass(frozen=True)
class Scene:
    """A validated scene. Use :func:`load_scene` to build one from a file."""

    name: str
    leds: LedRing
    plane: ImagingPlane
    effects: frozenset
    lens: Lens | None = None
    internal_bounces: int = 0
    depth_heights: tuple[float, ...] = (0.0,)
    trace: TraceDefaults = TraceDefaults()
    description: str = ""
    source: str = "<dict>"
    #: The lens design brief (``design`` section, see :mod:`sim.lensopt.brief`), or None.
    design: dict | None = None

    def has(self, effect: str) -> bool:
        """Whether the scene asks for ``effect`` (the lens effect also needs a lens)."""
        if effect not in EFFECTS:
            raise ValueError(f"unknown effect {effect!r}; expected one of {EFFECTS}")
        if effect == "lens" and self.lens is None:
            return False
        return effect in self.effects

    def with_effects(self, *, add=(), remove=()) -> "Scene":
        """A copy with effects added or removed, e.g. ``scene.with_effects(remove=["lens"])``."""
        eff = (set(self.effects) | set(add)) - set(remove)
        bad = eff - set(EFFECTS)
        if bad:
            raise ValueError(f"unknown effects {sorted(bad)}; expected a subset of {EFFECTS}")
        return replace(self, effects=frozenset(eff))

    def with_lens(self, **changes) -> "Scene":
        """A copy whose lens has the given fields changed (re-validated)."""
        if self.lens is None:
            raise ValueError("with_lens: the scene has no lens")
        d = scene_to_dict(self)
        where = {"arc_radius": ("side", "arc_radius"), "centre_rho": ("side", "centre_rho"),
                 "centre_z": ("side", "centre_z"), "cylinder_radius": ("side", "cylinder_radius"),
                 "top_radius": ("top", "radius"), "top_conic": ("top", "conic"), "apex_z": ("top", "apex_z"),
                 "bottom_z": ("bottom", "z")}
        for k, v in changes.items():
            if k not in where:
                raise ValueError(f"with_lens: unknown lens field {k!r}; expected one of {sorted(where)}")
            part, key = where[k]
            d["lens"][part][key] = float(v)
        return scene_from_dict(d, source=self.source)


def scene_names() -> list[str]:
    """Names of the shipped scenes (``sim/scenes/*.yaml``).

    Examples
    --------
    >>> {"default", "plano-sphere"} <= set(scene_names())
    True
    """
    return sorted(p.stem for p in _SCENES_DIR.glob("*.yaml"))


def resolve_scene_path(name_or_path: str | Path) -> Path:
    """A shipped scene's name (``default``) or a path to a YAML file -> the file's path."""
    p = Path(name_or_path)
    if p.suffix in (".yaml", ".yml") or p.exists():
        if not p.is_file():
            raise UserError(f"scene file {p}: not found")
        return p
    shipped = _SCENES_DIR / f"{name_or_path}.yaml"
    if shipped.is_file():
        return shipped
    raise UserError(f"scene {name_or_path!r}: not a shipped scene ({', '.join(scene_names())}) nor an existing file")


def load_scene(name_or_path: str | Path) -> Scene:
    """Load and validate a scene by shipped name or path.

    Examples
    --------
    >>> s = load_scene("default")
    >>> s.leds.count, s.has("lens"), round(s.lens.refractive_index, 2)
    (24, True, 1.49)
    """
    from data_schemas import SchemaError, read_yaml_file

    path = resolve_scene_path(name_or_path)
    try:
        data = read_yaml_file(path)
    except SchemaError as exc:
        raise UserError(f"scene file {exc}") from None
    return scene_from_dict(data, source=str(path))


def scene_from_dict(data: Any, source: str = "<dict>") -> Scene:
    """Validate a parsed scene mapping and build a :class:`Scene`.

    Raises :class:`pipeline.base.errors.UserError` naming ``source``, the field and what was expected.
    """
    import data_schemas

    if not isinstance(data, dict):
        raise UserError(f"scene file {source}: expected a mapping at the top level, got {type(data).__name__}")
    try:
        data_schemas.validate_config("scene", data, f"scene file {source}")
    except data_schemas.SchemaError as exc:
        raise UserError(str(exc)) from None

    led = data["leds"]
    count = int(led["count"])
    rgb = np.asarray(led.get("rgb", [[1.0, 1.0, 1.0]]), dtype=np.float64)
    if rgb.shape[0] == 1:
        rgb = np.repeat(rgb, count, axis=0)
    if rgb.shape != (count, 3):
        raise UserError(f"scene file {source}: field leds/rgb: expected 1 or {count} RGB triples, got {rgb.shape[0]}")
    leds = LedRing(count=count, radius=float(led["radius"]), height=float(led.get("height", 0.0)),
                   tilt_deg=float(led.get("tilt_deg", 0.0)), phase_deg=float(led.get("phase_deg", 0.0)),
                   emission_m=float(led.get("emission_m", 1.0)),
                   cone_half_angle_deg=float(led.get("cone_half_angle_deg", 60.0)), rgb=rgb)
    ip = data["imaging_plane"]
    plane = ImagingPlane(z=float(ip["z"]), size=(float(ip["size"][0]), float(ip["size"][1])),
                         resolution=(int(ip["resolution"][0]), int(ip["resolution"][1])))
    lens = _build_lens(data["lens"], source) if "lens" in data else None
    effects = frozenset(data["effects"])
    if "lens" in effects and lens is None:
        raise UserError(f"scene file {source}: field effects: 'lens' is listed but the scene has no lens section")
    if "dispersion" in effects and (lens is None or lens.abbe_number is None):
        raise UserError(f"scene file {source}: field lens/abbe_number: required when effects lists 'dispersion'")
    heights = tuple(float(h) for h in data.get("depth_heights", [0.0]))
    tr = TraceDefaults(**data.get("trace", {}))
    scene = Scene(name=str(data["name"]), description=str(data.get("description", "")), leds=leds, plane=plane,
                  effects=effects, lens=lens, internal_bounces=int(data.get("internal_bounces", 0)),
                  depth_heights=heights, trace=tr, source=source, design=data.get("design"))
    _check_layout(scene, source)
    return scene


def _build_lens(d: dict, source: str) -> Lens:
    side, top, bottom = d["side"], d["top"], d["bottom"]
    R, apex, zb = float(top["radius"]), float(top["apex_z"]), float(bottom["z"])
    k = float(top.get("conic", 0.0))
    e = 1.0 + k
    common = dict(refractive_index=float(d["refractive_index"]), top_radius=R, apex_z=apex, bottom_z=zb,
                  abbe_number=d.get("abbe_number"), top_aperture=top.get("clear_aperture"),
                  bottom_aperture=bottom.get("clear_aperture"), top_conic=k)
    if zb >= apex:
        raise UserError(f"scene file {source}: field lens/bottom/z: expected below lens/top/apex_z = {apex}, got {zb}")

    def top_rho_at(z):
        # The top's radius at height z (sphere or conic): rho^2 = 2 R w - (1 + k) w^2, w = apex - z.
        w = np.clip(apex - z, 0.0, None)
        return np.sqrt(np.clip(2.0 * R * w - e * w * w, 0.0, None))

    if "cylinder_radius" in side:
        rc = float(side["cylinder_radius"])
        if e * rc ** 2 >= R ** 2:
            widest = R / math.sqrt(e)
            raise UserError(f"scene file {source}: field lens/side/cylinder_radius: expected < the top's widest "
                            f"radius {widest:.6g}, got {rc}")
        # Depth of the rim below the apex: the smaller root of e w^2 - 2 R w + rc^2 = 0.
        rim_z = apex - (rc ** 2 / (R + math.sqrt(R ** 2 - e * rc ** 2)))
        if rim_z <= zb:
            raise UserError(f"scene file {source}: field lens/bottom/z: the top sphere meets the cylinder at "
                            f"z = {rim_z:.4g}, expected the bottom below that, got {zb}")
        return Lens(cylinder_radius=rc, rim_z=rim_z, rim_rho=rc, bottom_rho=rc, **common)

    r1, rho_c, zc = float(side["arc_radius"]), float(side["centre_rho"]), float(side["centre_z"])
    if abs(zb - zc) >= r1:
        raise UserError(f"scene file {source}: field lens/bottom/z: expected within the side arc's z range "
                        f"({zc - r1:.4g}, {zc + r1:.4g}), got {zb}")
    lens = Lens(arc_radius=r1, centre_rho=rho_c, centre_z=zc, **common)
    # The rim: where the side arc meets the top, by bisection on h = g - top_rho_at.
    z_hi = min(apex, zc + r1)
    h = lambda z: float(lens.side_rho(z) - top_rho_at(z))  # noqa: E731
    if not (h(zb) < 0.0 < h(z_hi)):
        raise UserError(f"scene file {source}: field lens/top: the side arc and the top do not meet above "
                        f"the bottom (side radius at the bottom {float(lens.side_rho(zb)):.4g} mm, top radius there "
                        f"{float(top_rho_at(zb)):.4g} mm); expected a closed convex lens")
    lo, hi = zb, z_hi
    for _ in range(200):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if h(mid) < 0.0 else (lo, mid)
    rim_z = 0.5 * (lo + hi)
    return replace(lens, rim_z=rim_z, rim_rho=float(lens.side_rho(rim_z)), bottom_rho=float(lens.side_rho(zb)))


def _check_layout(scene: Scene, source: str) -> None:
    lens, plane = scene.lens, scene.plane
    if lens is None:
        return
    top_z = lens.apex_z
    lowest_gel = plane.z - max(scene.depth_heights)
    if lowest_gel <= top_z:
        raise UserError(f"scene file {source}: field imaging_plane/z: expected the gel (z - max depth height = "
                        f"{lowest_gel:.4g}) above the lens apex z = {top_z:.4g}")
    pos, _ = scene.leds.geometry()
    rho = np.hypot(pos[:, 0], pos[:, 1])
    z = pos[:, 2]
    inside = (z >= lens.bottom_z) & (z <= lens.apex_z) & (rho <= lens.side_rho(np.clip(z, lens.bottom_z, lens.rim_z)))
    if np.any(inside):
        raise UserError(f"scene file {source}: field leds: expected every LED outside the lens, "
                        f"LED {int(np.argmax(inside))} is inside")


def scene_to_dict(scene: Scene) -> dict:
    """The scene as a plain mapping in the file's layout (round-trips through :func:`scene_from_dict`)."""
    L = scene.leds
    d: dict[str, Any] = {
        "name": scene.name,
        "description": scene.description,
        "leds": {"count": L.count, "radius": L.radius, "height": L.height, "tilt_deg": L.tilt_deg,
                 "phase_deg": L.phase_deg, "emission_m": L.emission_m,
                 "cone_half_angle_deg": L.cone_half_angle_deg, "rgb": np.asarray(L.rgb).tolist()},
        "imaging_plane": {"z": scene.plane.z, "size": list(scene.plane.size), "resolution": list(scene.plane.resolution)},
        "effects": sorted(scene.effects),
        "internal_bounces": scene.internal_bounces,
        "depth_heights": list(scene.depth_heights),
        "trace": {"rays": scene.trace.rays, "sampler": scene.trace.sampler, "seed": scene.trace.seed,
                  "intersection": scene.trace.intersection, "newton_iterations": scene.trace.newton_iterations},
    }
    if scene.design is not None:
        d["design"] = scene.design
    if scene.lens is not None:
        ln = scene.lens
        side = ({"arc_radius": ln.arc_radius, "centre_rho": ln.centre_rho, "centre_z": ln.centre_z}
                if ln.is_arc else {"cylinder_radius": ln.cylinder_radius})
        top = {"radius": ln.top_radius, "apex_z": ln.apex_z}
        if ln.top_conic != 0.0:
            top["conic"] = ln.top_conic
        if ln.top_aperture is not None:
            top["clear_aperture"] = ln.top_aperture
        bottom = {"z": ln.bottom_z}
        if ln.bottom_aperture is not None:
            bottom["clear_aperture"] = ln.bottom_aperture
        d["lens"] = {"refractive_index": ln.refractive_index, "side": side, "top": top, "bottom": bottom}
        if ln.abbe_number is not None:
            d["lens"]["abbe_number"] = ln.abbe_number
    return d
