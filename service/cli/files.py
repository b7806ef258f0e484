"""JSON documents a command reads from a file a person names (a result, a list of poses, a
board): read to a bounded size and parsed, with one line for whatever is wrong with them.

``/dev/zero`` or a file of gigabytes is cut off at ``MAX_JSON_BYTES`` instead of filling the
memory (a pipe still works, so a document can come through ``/dev/stdin``); JSON nested too
deep for the parser, or holding an integer of thousands of digits, is "not JSON" like any
other syntax error instead of an internal error.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

#: Larger files are no document cellcal reads (a result of 10,000 stations is about 30 MB).
MAX_JSON_BYTES = 256 * 2**20


def read_json(path: Path) -> Any:
    """The JSON document in ``path``; ``ValueError`` (one line) if it is larger than
    ``MAX_JSON_BYTES`` or not valid JSON, ``OSError`` if it cannot be read."""
    with open(path, "rb") as file:
        data = file.read(MAX_JSON_BYTES + 1)
    if len(data) > MAX_JSON_BYTES:
        raise ValueError(f"{path}: larger than {MAX_JSON_BYTES // 2**20} MB; not a document "
                         "cellcal reads")
    return parse_json(data, str(path))


def parse_json(text: str | bytes, where: str) -> Any:
    """``text`` parsed as JSON; ``ValueError`` ``where: not JSON (why)`` if it is not."""
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as exc:  # UnicodeDecodeError is a ValueError
        raise ValueError(f"{where}: not JSON ({str(exc).splitlines()[0]})") from None
