"""``iristac sim``: the ray tracer's commands (``sim_optics``), the renderer's (``sim_render``),
the photometric-stereo test objects (``sim_ps``) and the virtual sensors (``sim_sensor``)."""

from pipeline.cli import sim_optics, sim_ps, sim_render, sim_sensor
from pipeline.cli._common import make_group


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    sim_optics.register(group)
    sim_render.register(group)
    sim_ps.register(group)
    sim_sensor.register(group)
