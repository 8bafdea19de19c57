"""Exceptions. The CLI maps them to exit codes: InputError -> 2, RepairError -> 1."""

from __future__ import annotations


class MeshprepError(Exception):
    """Base class: a problem with the user's mesh or arguments, with a message naming the fix."""


class InputError(MeshprepError):
    """The input could not be read or the arguments are wrong (CLI exit code 2)."""


class RepairError(MeshprepError):
    """The mesh was read but could not be brought to the required state (CLI exit code 1)."""
