"""What the commands against a running service read from its answers, typed: an error, and
the ``state`` event that ends a run's or a calibration's stream. Imported when an answer is
read, so ``cellcal runs --help`` does not load pydantic."""

from __future__ import annotations

from typing import Any

from pydantic import BaseModel, model_validator


class Problem(BaseModel):
    """What went wrong, as the service says it: an error answer's ``{"detail", "code"}``
    (``service.api.openapi.ErrorBody``), a failed run's error, the ``shutdown`` event."""

    detail: str
    code: str = "error"

    def __str__(self) -> str:
        return f"{self.detail} ({self.code})"


class StateEvent(BaseModel):
    """The data of a stream's ``state`` event (``service.events.state_event``): the state; a
    run's station counts, stop reason and error, a calibration's or validation's error."""

    state: str
    error: Problem | None = None
    stations_captured: int = 0
    stations_skipped: int = 0
    stop_reason: str | None = None

    @model_validator(mode="before")
    @classmethod
    def _error_with_its_code(cls, data: Any) -> Any:
        """A calibration's or validation's event gives ``error`` (a sentence) and
        ``error_code`` side by side, a run's one ``{"detail", "code"}``: one Problem either
        way."""
        if isinstance(data, dict) and isinstance(data.get("error"), str):
            return {**data, "error": {"detail": data["error"],
                                      "code": data.get("error_code") or "error"}}
        return data
