"""Typed domain errors. Every message says what is wrong and what to do about it.

The CLI prints them as one line and exits non-zero; the API maps them to 4xx answers.
"""


class CloudgraphError(Exception):
    """Base of every error that is the caller's to fix (bad input, missing file, limits)."""


class SceneError(CloudgraphError):
    """The scene spec is invalid."""


class VolumeError(CloudgraphError):
    """A volume file cannot be read or used."""


class CacheError(CloudgraphError):
    """A cache file is missing, corrupt or of another format version."""


class ImageError(CloudgraphError):
    """An image cannot be read or compared."""
