"""Exceptions raised on misuse: bad configuration, bad arguments, unopenable sources.

Expected failures on a frame (no target, a rejected detection, no convergence) are
never exceptions; they are a :class:`visvec.data.Status` on the result.
"""

from __future__ import annotations


class VisvecError(Exception):
    """Base class of every error visvec raises on purpose.

    Attributes
    ----------
    args : tuple
        The message (one line naming the file, key, option or frame, and what was
        expected).
    """


class ConfigError(VisvecError, ValueError):
    """A rig or calibration file, or a parameter, is missing or has a wrong value
    (exit 2 on the command line).

    Attributes
    ----------
    args : tuple
        The message: it names the file, the key, the value found and what was
        expected.
    """


class SourceError(VisvecError, OSError):
    """A frame source (camera, video, folder, stream) cannot be opened or read at all
    (exit 3 on the command line).

    Attributes
    ----------
    args : tuple
        The message, naming the source.
    """


class InputFileError(VisvecError, ValueError):
    """A data file (truth, frames list, sidecar) has a bad row (exit 2).

    Attributes
    ----------
    args : tuple
        The message, naming the file and its line.
    """


class OutputError(VisvecError, OSError):
    """Rows cannot be written (a full disk, a file removed under the run): the message
    names the output and how many rows it holds, all of them complete."""


class NoOkRows(VisvecError):
    """A run that read frames (or samples) and gave not one ok row: exit 4, so that a
    script can tell it from a run that measured something."""
