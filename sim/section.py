"""The radial section of a scene with sample rays (the paper's Fig. 2), drawn to a PNG.

Left: the meridian plane ``y = 0`` of the optical frame with the lens profile, LED 0, the
gel and rays from LED 0 fanned across its cone in that plane, traced through the lens
(refraction at each surface, TIR drawn where it happens). Right (optional): the 24-LED flat-gel
image on the imaging plane, the paper's "transverse section".
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import torch

from pipeline.base.errors import UserError
from sim.optics.interface import reflect, refract
from sim.optics.lens import LensBody
from sim.optics.plane import plane_hit
from sim.scene import Scene, load_scene

__all__ = ["ray_paths", "draw_section"]


def ray_paths(scene: Scene, count: int = 25, max_bounces: int = 3) -> list[np.ndarray]:
    """Polylines (each (K, 3), optical mm) of ``count`` rays of LED 0 fanned in the plane ``y = 0``.

    Examples
    --------
    >>> paths = ray_paths(load_scene("default"), count=5)
    >>> len(paths), all(p.shape[1] == 3 and np.isfinite(p).all() for p in paths)
    (5, True)
    """
    pos, axes = scene.leds.geometry()
    src = pos[0]
    c = math.radians(scene.leds.cone_half_angle_deg)
    tilt = math.atan2(axes[0][0], axes[0][2])
    ang = np.linspace(-c, c, count) + tilt
    n = len(ang)
    dt = torch.float64
    d = (torch.tensor(np.sin(ang), dtype=dt), torch.zeros(n, dtype=dt), torch.tensor(np.cos(ang), dtype=dt))
    o = tuple(torch.full((n,), float(v), dtype=dt) for v in src)
    pts = [[np.array(src, dtype=float)] for _ in range(n)]
    alive = np.ones(n, bool)
    if scene.has("lens"):
        body = LensBody(scene.lens)
        ng = scene.lens.refractive_index
        t, sid, hit, _ = body.enter(o, d)
        p = tuple(o[i] + t * d[i] for i in range(3))
        d_in, _, _, _ = refract(d, body.normal(p, sid), 1.0 / ng)
        inside = hit.numpy().copy()
        for k in np.nonzero(inside)[0]:
            pts[k].append(np.array([float(c[k]) for c in p]))
        cur_p, cur_d = p, tuple(torch.where(hit, a, b) for a, b in zip(d_in, d))
        for _ in range(max_bounces + 1):
            if not inside.any():
                break
            t, sid, good = body.leave(cur_p, cur_d)
            q = tuple(cur_p[i] + t * cur_d[i] for i in range(3))
            nrm = body.normal(q, sid)
            inward = tuple(-c for c in nrm)
            dt_, _, _, tir = refract(cur_d, inward, ng)
            for k in np.nonzero(inside & good.numpy())[0]:
                pts[k].append(np.array([float(c[k]) for c in q]))
            tir_n = tir.numpy() & inside
            rd = reflect(cur_d, inward)
            new_d = tuple(torch.where(tir, a, b) for a, b in zip(rd, dt_))
            exited = inside & ~tir_n
            # Rays leaving the lens continue from q along the refracted direction.
            o = tuple(torch.where(torch.from_numpy(exited), a, b) for a, b in zip(q, o))
            d = tuple(torch.where(torch.from_numpy(exited), a, b) for a, b in zip(dt_, d))
            cur_p, cur_d = q, new_d
            inside = tir_n
        alive &= ~inside  # still trapped after max_bounces: drawn up to the last bounce
    x, y, t, ok = plane_hit(o, d, scene.plane.z)
    far = 1.5 * max(scene.plane.z, 1.0)
    # A ray that reaches the gel's plane only far off to the side (nearly horizontal, e.g. the
    # edge of a tilted LED's cone) is drawn as far as the others, not to its distant crossing.
    ok = ok & (t <= 4.0 * far)
    for k in range(n):
        if not alive[k]:
            continue
        if bool(ok[k]):
            pts[k].append(np.array([float(x[k]), float(y[k]), scene.plane.z]))
        else:
            pts[k].append(np.array([float(o[i][k] + far * d[i][k]) for i in range(3)]))
    return [np.array(p) for p in pts]


def draw_section(scene, out, *, rays: int = 25, image: bool = True, image_rays: int = 200_000) -> Path:
    """Draw the radial section (and the 24-LED image) of ``scene`` to the PNG ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    s = scene if isinstance(scene, Scene) else load_scene(scene)
    out = Path(out)
    if out.suffix.lower() != ".png":
        raise UserError(f"section: output {out} must be a .png file")
    ncols = 2 if image else 1
    fig, axs = plt.subplots(1, ncols, figsize=(7 * ncols, 5.5), squeeze=False)
    ax = axs[0, 0]
    if s.lens is not None:
        ln = s.lens
        z = np.linspace(ln.bottom_z, ln.rim_z, 100)
        rho_side = ln.side_rho(z)
        rt = np.linspace(0, ln.rim_rho, 100)
        zt = ln.top_z(rt)
        prof_r = np.concatenate([[0, ln.bottom_rho], rho_side, rt[::-1]])
        prof_z = np.concatenate([[ln.bottom_z, ln.bottom_z], z, zt[::-1]])
        # One polygon: the right half of the profile and its mirror image.
        ax.fill(np.concatenate([prof_r, -prof_r[::-1]]), np.concatenate([prof_z, prof_z[::-1]]), color="#9ecae1",
                alpha=0.5, lw=1, ec="#3182bd", label="lens")
    half = s.plane.size[0] / 2
    ax.plot([-half, half], [s.plane.z, s.plane.z], color="k", lw=3, label="gel (imaging plane)")
    pos, _ = s.leds.geometry()
    for path in ray_paths(s, rays):
        ax.plot(path[:, 0], path[:, 2], color="#e6550d", lw=0.7, alpha=0.8)
    ax.plot(pos[0, 0], pos[0, 2], "o", color="#de2d26", ms=7, label="LED 0")
    if s.leds.count > 1:
        opp = np.argmin(np.abs(np.arctan2(pos[:, 1], pos[:, 0]) - math.pi) % (2 * math.pi))
        ax.plot(pos[opp, 0], pos[opp, 2], "o", color="#fc9272", ms=6)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("z (mm)")
    ax.set_aspect("equal")
    ax.set_title(f"{s.name}: radial section, {rays} rays of LED 0" + ("" if s.has("lens") else " (no lens)"))
    ax.set_ylim(min(-2.0, s.leds.height - 2), s.plane.z + 8)
    ax.legend(loc="lower left", fontsize=8)
    if image:
        from sim.optics.grid import PixelGrid
        from sim.optics.metrics import image_metrics, pattern_image
        from sim.optics.multisource import trace_all

        # Sobol rays for the picture: the paper's deterministic grid puts rays on rings and
        # spokes that alias with the pixel grid into moire. (The tracer directly, not
        # sim.lens_design, which draws sections itself.)
        tr = trace_all(s, PixelGrid.from_plane(s.plane), rays=image_rays, sampler="sobol", vector=False)
        E = tr.E[0].astype(np.float64)
        r = image_metrics(E, s.leds.rgb, tr.fraction_on_grid)
        img = pattern_image(E, s.leds.rgb).mean(axis=2) * 1e6
        ax2 = axs[0, 1]
        hw, hh = s.plane.size[0] / 2, s.plane.size[1] / 2
        # origin="lower": y grows upward as in the optical frame's x-y plane seen from the camera side.
        im = ax2.imshow(img, origin="lower", extent=(-hw, hw, -hh, hh), cmap="inferno")
        fig.colorbar(im, ax=ax2, label="irradiance, W/m^2 per W per LED")
        leds = f"{s.leds.count} LED" + ("s" if s.leds.count > 1 else "")
        ax2.set_title(f"{leds} on the gel ({image_rays:,} Sobol rays): {100 * r['fraction_on_screen']:.1f}% on "
                      f"screen, CV {r['uniformity_cv']:.2f}")
        ax2.set_xlabel("x (mm)")
        ax2.set_ylabel("y (mm)")
    from sim.figures import save_figure

    return save_figure(fig, out, dpi=110)
