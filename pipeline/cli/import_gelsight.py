"""``iristac import gelsight-npz`` (not implemented yet: the calibration issue)."""

from pipeline.cli._common import not_implemented


def register(group):
    not_implemented(group, "gelsight-npz", "import GelSight-style ball presses (npz) as a capture", "the calibration issue")
