"""``iristac cache ls|verify|gc|clear`` (the store is being built in the foundation issue)."""

from pipeline.cli._common import make_group, not_implemented


def register(sub, name, help_text):
    _, group = make_group(sub, name, help_text)
    for n in ("ls", "verify", "gc", "clear"):
        not_implemented(group, n, f"cache {n}", "the foundation issue")
