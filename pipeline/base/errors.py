"""Errors that the CLI reports as one clear line instead of a traceback."""

from __future__ import annotations


class UserError(Exception):
    """Bad input from the user: a missing file, a malformed config, an impossible request.

    The message must say which file or option, which field, and what was expected.
    """


class NotImplementedYet(UserError):
    """A command the product will have but does not have yet."""
