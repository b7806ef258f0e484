"""The requests the service refuses: one exception family, mapped to HTTP in ``service.app``.

Domain code raises these (never an HTTP exception), so the same rules serve the REST API, the
background threads and the tests; ``code`` is stable for programs, the message is for people.
"""

from __future__ import annotations


class ServiceError(Exception):
    """A request the service refuses; ``code`` is stable, the message is for people."""

    code = "service_error"

    def __init__(self, detail: str, *, code: str | None = None) -> None:
        super().__init__(detail)
        self.detail = detail
        if code is not None:
            self.code = code


class NotFoundError(ServiceError):
    code = "not_found"


class ConflictError(ServiceError):
    code = "conflict"


class UnprocessableError(ServiceError):
    code = "invalid_request"


class AuthError(ServiceError):
    code = "unauthorized"
