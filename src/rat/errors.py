"""The one error type that reaches a user.

Every mistake a user can make (an unknown task, a victim that does not fit the environment,
a corrupted checkpoint, a missing optional dependency) raises :class:`RatError` with a
one-line message that names the problem *and* the fix. The CLI prints it and exits with 2.
"""

from __future__ import annotations


class RatError(Exception):
    """A user-facing error: one line saying what is wrong and how to fix it."""

    exit_code = 2


def require(module: str, extra: str):
    """Import an optional dependency, or say which extra installs it."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise RatError(
            f"optional dependency '{module}' is not installed; install it with "
            f"`pip install 'rat[{extra}]'`"
        ) from exc
