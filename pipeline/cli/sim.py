"""``iristac sim``: the ray tracer's commands (``sim_optics``), the renderer's (``sim_render``) and
the photometric-stereo test objects (``sim_ps``)."""

from pipeline.cli import sim_optics, sim_ps, sim_render
from pipeline.cli._common import make_group


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    sim_optics.register(group)
    sim_render.register(group)
    sim_ps.register(group)
