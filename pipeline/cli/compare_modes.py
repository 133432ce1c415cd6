"""CLI command (not implemented yet: the pipeline-run issue)."""

from pipeline.cli._common import not_implemented


def register(sub, name, help_text):
    not_implemented(sub, name, help_text, "the pipeline-run issue")
