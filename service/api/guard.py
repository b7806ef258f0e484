"""The request guard: the API key and the body size, both checked before a body is read.

FastAPI reads and parses a JSON body before it runs a route's dependencies, so a key checked in
a dependency comes too late: a 60 MB body without any key cost seconds and a gigabyte of memory
(issue 11). :class:`RequestGuard` is plain ASGI middleware in front of everything:

* every path but the open ones (``is_open``) needs ``Authorization: Bearer <key>``; a
  refusal is sent without reading a byte of the body;
* a ``Content-Length`` beyond the limit is refused the same way (413); a body without one
  (chunked) is counted while the application reads it and cut off at the limit, so at most the
  limit plus one chunk is ever held.

Refusals are :class:`service.errors.ServiceError` subclasses, turned into the JSON error body by
the ``refuse`` callable the app passes in (``service.app`` maps every error in one place).
"""

from __future__ import annotations

import contextlib
import secrets
from collections.abc import Callable

from pydantic import SecretStr
from starlette.responses import Response
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from service.errors import AuthError, ServiceError

#: Paths served without a key: liveness, the API documentation and the web page (its data
#: calls need the key).
OPEN_PATHS = frozenset({"/health", "/docs", "/docs/oauth2-redirect", "/redoc", "/openapi.json",
                        "/", "/ui", "/redoc/bundle.js", "/favicon.ico"})
#: Static assets served without a key: the web page's and the offline docs' (no data in them).
OPEN_PREFIXES = ("/ui/", "/static-offline-docs/")


def is_open(path: str) -> bool:
    """True for a path served without the API key."""
    return path in OPEN_PATHS or path.startswith(OPEN_PREFIXES)


class PayloadTooLargeError(ServiceError, code="payload_too_large"):
    """A request body beyond ``Settings.max_body_bytes`` (413)."""


def bearer_token(authorization: str | None) -> str | None:
    """The token of an ``Authorization: Bearer <token>`` header; None for others or none."""
    scheme, _, token = (authorization or "").partition(" ")
    return token.strip() or None if scheme.lower() == "bearer" else None


def check_api_key(api_key: SecretStr | None, token: str | None) -> None:
    """Accept only the configured key as bearer ``token``; raise :class:`AuthError` otherwise."""
    if api_key is None:
        raise AuthError("This service has no API key configured; set CELLCAL_API_KEY and "
                        "restart it.", code="no_api_key")
    if token is None:
        raise AuthError("Missing credentials: send 'Authorization: Bearer <CELLCAL_API_KEY>'.")
    if not secrets.compare_digest(token.encode(), api_key.get_secret_value().encode()):
        raise AuthError("Invalid API key.", code="invalid_api_key")


def too_large(limit: int) -> PayloadTooLargeError:
    return PayloadTooLargeError(f"Request body larger than {limit} bytes "
                                "(CELLCAL_MAX_BODY_BYTES).")


class _BodyCutOffError(Exception):
    """Raised into the application when a streamed body passes the limit."""


class RequestGuard:
    """ASGI middleware: key and body size checked before the application reads the body.

    Parameters
    ----------
    app : the application behind the guard.
    api_key : the key every call but the open paths (``is_open``) need (None: every such
        call is refused).
    max_body_bytes : largest request body accepted.
    refuse : turns a :class:`ServiceError` into the response sent instead.
    """

    def __init__(self, app: ASGIApp, *, api_key: SecretStr | None, max_body_bytes: int,
                 refuse: Callable[[ServiceError], Response]) -> None:
        self.app = app
        self.api_key = api_key
        self.max_body_bytes = max_body_bytes
        self.refuse = refuse

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        headers = {k.decode("latin-1").lower(): v.decode("latin-1")
                   for k, v in scope["headers"] if k.lower() in (b"authorization",
                                                                 b"content-length")}
        try:
            if not is_open(scope["path"]):
                check_api_key(self.api_key, bearer_token(headers.get("authorization")))
            length = headers.get("content-length", "")
            if length.isdigit() and int(length) > self.max_body_bytes:
                raise too_large(self.max_body_bytes)
        except ServiceError as exc:
            await self.refuse(exc)(scope, receive, send)
            return
        await self._bounded(scope, receive, send)

    async def _bounded(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Run the application with the body counted; past the limit, answer 413 instead."""
        received = 0
        cut_off = False
        started = False

        async def counting_receive() -> Message:
            nonlocal received, cut_off
            message = await receive()
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                if received > self.max_body_bytes:
                    cut_off = True
                    raise _BodyCutOffError
            return message

        async def guarded_send(message: Message) -> None:
            nonlocal started
            if cut_off:  # whatever the application answers to the cut, the client gets 413
                return
            started = started or message["type"] == "http.response.start"
            await send(message)

        with contextlib.suppress(_BodyCutOffError):
            await self.app(scope, counting_receive, guarded_send)
        if cut_off and not started:
            await self.refuse(too_large(self.max_body_bytes))(scope, receive, send)
