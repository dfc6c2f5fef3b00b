"""Typed errors shared by every floor.

Each error is catchable both as a station error and as the builtin family it belongs to
(ophyd's `LimitError(ValueError, ...)` pattern), and carries the process exit code the CLI
returns for it: 2 bad input or usage, 3 device or hardware fault (a full disk too), 1 gate failed.
Anything else reaching the CLI is a fault in station itself: INTERNAL_EXIT_CODE.
"""

from __future__ import annotations


INTERNAL_EXIT_CODE = 4  # an exception no StationError names: a bug, reported without a traceback


class StationError(Exception):
    """Base of every error this package raises on purpose."""

    exit_code: int = 2


class BadInputError(ValueError, StationError):
    """A file, folder or argument is malformed; the message names it and what is wrong."""

    exit_code = 2


class ScanFolderError(BadInputError):
    """A scan folder breaks the contract (missing stage output, path escaping the folder, ...)."""


class DiskFullError(OSError, StationError):
    """Not enough free space to start or finish a stage without risking a partial write."""

    exit_code = 3


class DeviceError(IOError, StationError):
    """A hardware device (turntable, camera) failed or answered something unexpected."""

    exit_code = 3


class DeviceTimeoutError(TimeoutError, DeviceError):
    """The device did not answer within its deadline (the device timed out, not the caller)."""

    exit_code = 3


class DeviceDisconnectedError(DeviceError):
    """The device vanished (port closed, USB unplugged) during an operation."""

    exit_code = 3


class TrainingError(RuntimeError, StationError):
    """Training cannot go on (NaN/inf in a tensor, divergence); the message names step and tensor."""

    exit_code = 2


class GateFailedError(StationError):
    """The asset was written but failed the quality gate and is quarantined."""

    exit_code = 1


# Untrusted file formats (station/formats, station/ngs/checkpoint_io.py) ---------------------------
class FormatError(ScanFolderError):
    """A file of a scan folder or a source dataset breaks its format; `path` and `field` say where."""

    def __init__(self, path: object, field: str | None, problem: str):
        super().__init__(path, field, problem)  # all three in args: the error pickles across processes
        self.path, self.field, self.problem = path, field, problem

    def __str__(self) -> str:
        return f"{self.path}: {self.field}: {self.problem}" if self.field else f"{self.path}: {self.problem}"


class InputTooLargeError(FormatError):
    """A file claims more than a configured limit (pixels, bytes, nesting): refused before it is decoded."""


class CheckpointError(FormatError):
    """A model file (checkpoint.pt, surface.pt, infill.pt) is truncated, garbage or has the wrong layout."""
