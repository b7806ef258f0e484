"""The requests the service refuses: one exception family, mapped to HTTP in ``service.app``.

Domain code raises these (never an HTTP exception), so the same rules serve the REST API, the
background threads and the tests; ``code`` is stable for programs, the message is for people
(``drivers.errors.CodedError``).
"""

from __future__ import annotations

from drivers.errors import CodedError


class ServiceError(CodedError, code="service_error"):
    """A request the service refuses (400 unless a subclass says otherwise)."""


class NotFoundError(ServiceError, code="not_found"):
    """No such run, station, calibration or validation (404)."""


class ConflictError(ServiceError, code="conflict"):
    """The request does not fit the current state: the robot is busy, the run is in the wrong
    state (409)."""


class UnprocessableError(ServiceError, code="invalid_request"):
    """The request is well-formed but cannot be done (422)."""


class AuthError(ServiceError, code="unauthorized"):
    """Missing or wrong API key (401)."""


class QueueFullError(ServiceError, code="queue_full"):
    """Too much work is already waiting; retry later (429)."""


class NotReadyError(ServiceError, code="not_ready"):
    """The answer is still being worked on (a report rendering): 503 with ``Retry-After``
    (``retry_after_s``), so a client asks again instead of holding a request open."""

    def __init__(self, message: str, *, retry_after_s: int, code: str | None = None) -> None:
        super().__init__(message, code=code)
        self.retry_after_s = retry_after_s
