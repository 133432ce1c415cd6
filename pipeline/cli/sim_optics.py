"""``iristac sim trace|section|optimize-lens|synthesize`` (not implemented yet: the ray tracer issue)."""

from pipeline.cli._common import not_implemented


def register(group):
    for name, text in [
        ("trace", "trace a scene and report flux on screen and uniformity"),
        ("section", "draw the radial section of a scene with sample rays to a PNG"),
        ("optimize-lens", "search lens shapes for flux on screen under a uniformity constraint"),
    ]:
        not_implemented(group, name, text, "the ray tracer issue")
