"""One-line messages for configuration files validated by pydantic (device configurations such
as the mock cell's scene, station sets): ``where: what``, never a multi-line dump."""

from __future__ import annotations

from pydantic import ValidationError


def describe_validation_error(exc: ValidationError) -> str:
    """The first pydantic error as ``where: what`` (e.g. ``stations[3].tcp_pose[2]: …``)."""
    err = exc.errors()[0]
    cause = err.get("ctx", {}).get("error") if err["type"] == "value_error" else None
    msg = str(cause) if isinstance(cause, ValueError) else err["msg"]
    where = ""
    for part in err["loc"]:
        where += f"[{part}]" if isinstance(part, int) else (f".{part}" if where else str(part))
    more = f" (and {exc.error_count() - 1} more problems)" if exc.error_count() > 1 else ""
    return f"{where or 'file'}: {msg}{more}"
