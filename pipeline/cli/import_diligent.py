"""``iristac import diligent`` (not implemented yet: the reconstruction issue)."""

from pipeline.cli._common import not_implemented


def register(group):
    not_implemented(group, "diligent", "import a DiLiGenT-layout folder as a capture", "the reconstruction issue")
