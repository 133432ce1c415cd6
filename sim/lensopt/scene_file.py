"""Write an optimised design as a scene file that ``iristac sim trace`` can load."""

from __future__ import annotations

from pathlib import Path

__all__ = ["write_scene_file"]


def write_scene_file(scene, path, result: dict | None = None) -> Path:
    """Write ``scene`` as YAML to ``path`` (atomically), headed by a comment with how it was found.

    The file round-trips through :func:`sim.scene.load_scene` (checked before it is moved into
    place, so a file that would not load is never left behind).

    Examples
    --------
    >>> import tempfile, os
    >>> from sim.scene import load_scene
    >>> p = write_scene_file(load_scene("default-v1"), os.path.join(tempfile.mkdtemp(), "s.yaml"))
    >>> load_scene(p).lens.arc_radius
    13.5
    """
    import yaml

    from sim.scene import load_scene, scene_to_dict

    path = Path(path)
    lines = [f"# {scene.name}: written by `iristac sim optimize-lens`."]
    if result is not None:
        fmt = lambda v: "-" if v is None else f"{v:.4g}"  # noqa: E731
        lines += [f"# Objective {result['objective']}"
                  + (f" for modes {', '.join(result['modes'])}" if result.get("modes") else "")
                  + f", constraints {result['constraints'] or 'none'}; {result['method']}, "
                  f"{result['evaluations']} designs in {result['seconds']:.1f} s.",
                  f"# Confirmed with {result['confirm_rays']:,} rays: {100 * result['fraction_on_screen']:.2f} % on "
                  f"screen, 24-LED CV {result['uniformity_cv']:.4f}, valid fraction {fmt(result['valid_fraction'])}, "
                  f"median condition {fmt(result['median_condition'])}.",
                  f"# Bare LEDs: {100 * result['bare']['fraction_on_screen']:.2f} % on screen, "
                  f"CV {result['bare']['uniformity_cv']:.4f}."]
    d = scene_to_dict(scene)
    d.pop("design", None)  # the brief that found it belongs to the scene it started from
    rgb = d["leds"]["rgb"]
    if all(row == rgb[0] for row in rgb):
        d["leds"]["rgb"] = [rgb[0]]  # one triple for every LED, as the shipped scenes write it
    for part in d.get("lens", {}).values():
        if isinstance(part, dict):
            for k, v in part.items():
                part[k] = round(float(v), 4)  # 0.1 um: far below any workshop's tolerance
    text = "\n".join(lines) + "\n" + yaml.safe_dump(d, sort_keys=False, default_flow_style=None, width=110)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text(text)
    try:
        load_scene(tmp)
    except Exception:
        tmp.unlink(missing_ok=True)
        raise
    tmp.replace(path)
    return path
