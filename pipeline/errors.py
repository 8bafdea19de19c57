"""Exceptions for user mistakes.

A :class:`UserError` is a problem with what the user gave us (a config, a scan folder, an object file),
never a bug. Its message names the file or key, the bad value and the fix. The CLI prints it on one
line, without a traceback. Anything else that escapes a stage is a bug and is reported with its
traceback in the log.
"""

from __future__ import annotations


class UserError(Exception):
    """A mistake in the user's input; the message says what and how to fix it."""


class ConfigError(UserError):
    """A bad configuration value, key or file (exit code 2). ``key``: the ``table.key`` (or table) it is
    about, where there is one, so that the loader can say whether the config file or ``--set`` gave it."""

    def __init__(self, message: str, key: str | None = None):
        super().__init__(message)
        self.key = key


class InputError(UserError):
    """A bad input file: scan frame, pose, intrinsics, mesh or object model."""
