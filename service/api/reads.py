"""The read endpoints of a resource stored under a parent, written once: the listing under the
parent (a run's calibrations, a calibration's validations) and one item by its id.

Each path has one id parameter, and the ``store`` function it calls takes that id under the same
keyword (``/runs/{run_id}/calibrations`` -> ``queries.list_calibrations(s, run_id=...)``); unknown
ids are the store's 404. The public schema is validated from the stored row.
"""

# No ``from __future__ import annotations``: FastAPI reads the endpoints' annotations, and
# ``Path(alias=...)`` refers to the factory's local names.

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import APIRouter, Path
from pydantic import BaseModel

from service.api.deps import SessionDep


@dataclass(frozen=True)
class Read:
    """One ``GET`` endpoint: its path, the store function it calls, the name (operation id,
    summary) and the description of the OpenAPI document."""

    path: str
    fetch: Callable[..., Any]
    name: str
    doc: str

    @property
    def id_name(self) -> str:
        """The path's id parameter, also the keyword of ``fetch``."""
        (name,) = re.findall(r"\{(\w+)\}", self.path)
        return name


def add_reads(router: APIRouter, model: type[BaseModel], *, listing: Read, item: Read) -> None:
    """Add ``GET listing.path`` (the rows as a list of ``model``) and ``GET item.path`` (one row
    as ``model``) to ``router``."""
    parent_id, item_id = listing.id_name, item.id_name

    def list_rows(parent: Annotated[str, Path(alias=parent_id)],
                  session: SessionDep) -> list[BaseModel]:
        return [model.model_validate(row) for row in listing.fetch(session, **{parent_id: parent})]

    def get_row(key: Annotated[str, Path(alias=item_id)], session: SessionDep) -> BaseModel:
        return model.model_validate(item.fetch(session, **{item_id: key}))

    router.add_api_route(listing.path, list_rows, methods=["GET"], response_model=list[model],
                         name=listing.name, description=listing.doc)
    router.add_api_route(item.path, get_row, methods=["GET"], response_model=model,
                         name=item.name, description=item.doc)
