"""Errors that the CLI turns into one clear line on stderr and a non-zero exit."""


class MeshsealError(Exception):
    """Base class for user-facing errors (bad input, bad arguments)."""


class MeshError(MeshsealError):
    """A mesh file is missing, unreadable, corrupt or unusable."""
