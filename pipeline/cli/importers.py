"""``iristac import``: one subcommand module per foreign format."""

from pipeline.cli._common import make_group
from pipeline.cli import import_gelsight, import_diligent, import_images


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    import_gelsight.register(group)
    import_diligent.register(group)
    import_images.register(group)
