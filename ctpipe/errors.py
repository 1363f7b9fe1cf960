"""Exceptions that carry a one-line message meant for the user.

The CLI prints ``str(exc)`` of these on one line and exits with status 2 (1 for
:class:`OutputError` and :class:`ClusterError`, faults of the machine rather than of the user's
input: the same command works once they are mended); anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations

__all__ = ["CtpipeError", "ConfigError", "InputError", "ResourceError", "PluginError", "EstimationError", "OutputError",
           "ClusterError"]


class CtpipeError(Exception):
    """Base class of errors caused by what the user gave ctpipe."""


class ConfigError(CtpipeError, ValueError):
    """A configuration value is wrong; the message starts with its YAML path."""


class InputError(CtpipeError, ValueError):
    """An input array, file or geometry is not usable."""


class ResourceError(InputError):
    """A request needs more memory than the machine has available."""


class PluginError(CtpipeError):
    """A plugin registered something inconsistent (duplicate or malformed stage)."""


class EstimationError(CtpipeError):
    """The data do not determine what was asked (too few matches, no consensus)."""


class OutputError(CtpipeError):
    """A result could not be written (the disk or the quota is full); earlier results are unchanged."""


class ClusterError(CtpipeError):
    """The Dask cluster cannot go on with the run: its scheduler or every worker is gone, or the
    workers running one task keep dying. Nothing is written."""
