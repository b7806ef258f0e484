"""What the commands against a running service (``cellcal runs``, ``cellcal calibrations``)
share: where the service is (``--url``, ``--api-key`` or ``CELLCAL_URL``, ``CELLCAL_API_KEY``),
one HTTP call whose failure is one line for people (``ServiceCallError``), server-sent events
followed across reconnects (``Last-Event-ID``), and a progress bar fed by them.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import httpx
from tqdm import tqdm

from service.cli.errors import ServiceCallError

if TYPE_CHECKING:
    from service.cli.answers import StateEvent

DEFAULT_URL = "http://127.0.0.1:8000"
#: Reconnects of an event stream in a row (each after a dropped connection) before giving up.
MAX_RECONNECTS = 5
#: Seconds an event stream may stay silent: the service sends a keep-alive every 15 s.
STREAM_READ_TIMEOUT_S = 60.0


@dataclass(frozen=True)
class Event:
    """One server-sent event: its stream id (None for the unstored ``shutdown``), type and
    data."""

    id: int | None
    type: str
    data: dict[str, Any]


def add_connection_arguments(parser: argparse.ArgumentParser) -> None:
    """``--url`` and ``--api-key``, defaulting to ``CELLCAL_URL`` and ``CELLCAL_API_KEY``."""
    parser.add_argument("--url", default=os.getenv("CELLCAL_URL", DEFAULT_URL),
                        help=f"the service (default: CELLCAL_URL or {DEFAULT_URL})")
    parser.add_argument("--api-key", default=os.getenv("CELLCAL_API_KEY"),
                        help="the service's API key (default: CELLCAL_API_KEY)")


def add_list_and_show(actions: argparse._SubParsersAction, things: str, show_help: str,
                      id_name: str) -> argparse.ArgumentParser:
    """The ``list`` (``--limit``) and ``show ID`` actions of a command; the ``list`` parser,
    for its filters."""
    listing = actions.add_parser("list", help=f"{things}, newest first")
    listing.add_argument("--limit", type=int, default=50, help="at most this many (default 50)")
    show = actions.add_parser("show", help=show_help)
    show.add_argument(id_name, metavar=id_name.upper())
    return listing


@dataclass(frozen=True)
class Service:
    """A running cellcal service: ``url`` and the API ``key``."""

    url: str
    key: str | None
    timeout_s: float = 30.0

    @classmethod
    def from_args(cls, args: argparse.Namespace) -> Service:
        return cls(url=args.url.rstrip("/"), key=args.api_key)

    def _headers(self) -> dict[str, str]:
        return {} if self.key is None else {"Authorization": f"Bearer {self.key}"}

    def call(self, method: str, path: str, *, body: Any = None,
             params: dict[str, Any] | None = None) -> httpx.Response:
        """The answer to one request; ServiceCallError for no answer or an error status."""
        try:
            r = httpx.request(method, self.url + path, json=body, params=params,
                              headers=self._headers(), timeout=self.timeout_s)
        except httpx.HTTPError as exc:
            raise self._unreachable(exc) from None
        if r.status_code >= 400:
            raise ServiceCallError(describe_error(r))
        return r

    def fetch(self, path: str, **params: Any) -> Any:
        """GET ``path`` as JSON (parameters that are None left out)."""
        return self.call("GET", path, params={k: v for k, v in params.items()
                                               if v is not None}).json()

    def post(self, path: str, body: Any = None, **params: Any) -> Any:
        """POST ``body`` as JSON to ``path``; the JSON answer."""
        return self.call("POST", path, body=body, params=params or None).json()

    def events(self, path: str) -> Iterator[Event]:
        """The events of a stream until the service ends it; a dropped connection is
        resumed with ``Last-Event-ID``, so no event is lost or repeated. A service that
        shuts down first ends the stream with ``shutdown``: ServiceCallError."""
        last: int | None = None
        failures = 0
        while True:
            headers = self._headers() | ({} if last is None else {"Last-Event-ID": str(last)})
            timeout = httpx.Timeout(self.timeout_s, read=STREAM_READ_TIMEOUT_S)
            try:
                with httpx.stream("GET", self.url + path, headers=headers,
                                  timeout=timeout) as r:
                    if r.status_code >= 400:
                        r.read()
                        raise ServiceCallError(describe_error(r))
                    for event in parse_events(r.iter_lines()):
                        if event.type == "shutdown":
                            from service.cli.answers import Problem

                            raise ServiceCallError(Problem.model_validate(event.data).detail)
                        last, failures = event.id, 0
                        yield event
                return
            except httpx.TransportError as exc:
                failures += 1
                if failures > MAX_RECONNECTS:
                    raise self._unreachable(exc) from None

    def _unreachable(self, exc: httpx.HTTPError) -> ServiceCallError:
        if isinstance(exc, httpx.TimeoutException):
            return ServiceCallError(f"the service at {self.url} did not answer in time "
                                    f"({type(exc).__name__})")
        why = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        return ServiceCallError(f"cannot reach the service at {self.url} ({why}); is "
                                "'cellcal serve' running there?")


def describe_error(r: httpx.Response) -> str:
    """An error answer in one line: the service's detail, the status and the code."""
    from pydantic import ValidationError

    from service.cli.answers import Problem

    try:
        problem = Problem.model_validate_json(r.content)
        detail, code = problem.detail, problem.code
    except ValidationError:
        detail, code = (r.text.strip().splitlines() or [r.reason_phrase])[0], "error"
    text = f"{detail} (HTTP {r.status_code} {code})"
    if r.status_code == 401:
        text += "; give the service's key with --api-key or CELLCAL_API_KEY"
    return text


def parse_events(lines: Iterator[str]) -> Iterator[Event]:
    """Server-sent events from the lines of a ``text/event-stream`` (comments and fields other
    than ``id``, ``event`` and ``data`` skipped)."""
    event_id: int | None = None
    kind, data = "message", None
    for line in lines:
        if line.startswith(":"):
            continue
        if line:
            key, _, value = line.partition(":")
            value = value.removeprefix(" ")
            if key == "id":
                event_id = int(value)
            elif key == "event":
                kind = value
            elif key == "data":
                data = value
            continue
        if data is not None:
            yield Event(id=event_id, type=kind, data=json.loads(data))
        event_id, kind, data = None, "message", None


#: What a stream's event says of the work done: (count done, count in all or None).
Progress = Callable[[Event], "tuple[int, int | None] | None"]


def follow(service: Service, path: str, *, total: int | None, unit: str,
           progress: Progress = lambda event: None) -> StateEvent:
    """Follow an event stream with a progress bar on stderr (elapsed time, the count
    ``progress(event)`` says is done, None: no change, and the latest message or state)
    until the service ends the stream; its last ``state`` event."""
    from service.cli.answers import StateEvent

    final: StateEvent | None = None
    with tqdm(total=total or None, unit=unit, file=sys.stderr, dynamic_ncols=True,
              leave=True) as bar:
        for event in service.events(path):
            step = progress(event)
            if step is not None:
                if step[1] is not None and step[1] != bar.total:
                    bar.total = step[1]
                bar.update(step[0] - bar.n)
            if "message" in event.data:
                bar.set_postfix_str(str(event.data["message"]))
            if event.type == "state":
                final = StateEvent.model_validate(event.data)
                bar.set_postfix_str(final.state)
    if final is None:
        raise ServiceCallError(f"the event stream {path} ended without a state")
    return final


def print_json(value: Any) -> None:
    """``value`` as indented JSON on stdout."""
    sys.stdout.write(json.dumps(value, indent=2) + "\n")


def _cell(value: Any) -> str:
    """A table cell: - for None, a float to 3 decimals (an RMS in px, not 17 digits)."""
    if value is None:
        return "-"
    return f"{value:.3f}" if isinstance(value, float) else str(value)


def print_table(rows: list[dict[str, Any]], columns: list[str]) -> None:
    """Rows (a listing's JSON items, each with every column) as a plain text table on stdout
    (None shown as -, numbers with 3 decimals)."""
    cells = [[_cell(row[c]) for c in columns] for row in rows]
    widths = [max([len(c), *(len(r[i]) for r in cells)]) for i, c in enumerate(columns)]
    for line in ([columns, *cells]):
        sys.stdout.write("  ".join(v.ljust(w) for v, w in zip(line, widths, strict=True))
                         .rstrip() + "\n")
