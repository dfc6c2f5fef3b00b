"""Action status objects (ophyd's split): whoever waits gets the device's failure re-raised."""

from __future__ import annotations

import threading

from station.turntable.errors import WaitTimeoutError


class MoveStatus:
    """Completion of one action (ophyd style): `wait()` returns the result or re-raises the failure."""

    def __init__(self, description: str) -> None:
        self.description = description
        self._done = threading.Event()
        self._result: tuple[float, float] | None = None
        self._error: BaseException | None = None

    @property
    def done(self) -> bool:
        return self._done.is_set()

    @property
    def success(self) -> bool:
        return self._done.is_set() and self._error is None

    @property
    def exception(self) -> BaseException | None:
        return self._error

    def _finish(self, result: tuple[float, float] | None, error: BaseException | None) -> None:
        self._result, self._error = result, error
        self._done.set()

    def wait(self, timeout: float | None = None) -> tuple[float, float]:
        """Position reached (turntable, tilt) in degrees; WaitTimeoutError if *we* stopped waiting."""
        if not self._done.wait(timeout):
            raise WaitTimeoutError(f"stopped waiting after {timeout} s for {self.description}; it is still running")
        if self._error is not None:
            raise self._error
        return self._result  # type: ignore[return-value]  # set together with _done when no error
