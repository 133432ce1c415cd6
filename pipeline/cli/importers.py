"""``iristac import``: one subcommand module per foreign format."""

from pipeline.cli import import_diligent, import_gelsight, import_images
from pipeline.cli._common import make_group


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    import_gelsight.register(group)
    import_diligent.register(group)
    import_images.register(group)
