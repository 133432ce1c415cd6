"""``iristac sim render|modes`` (not implemented yet: the renderer issue)."""

from pipeline.cli._common import not_implemented


def register(group):
    for name, text in [
        ("modes", "list the lighting modes"),
        ("render", "render a height map under a lighting mode"),
    ]:
        not_implemented(group, name, text, "the renderer issue")
