"""Every value of a result document reaches the report escaped (issue 22, row 9).

A result file is user input once it leaves cellcal: ``cellcal report`` on a hand-edited
``result.json`` used to copy ``camera.image_size`` and ``stations[].n_corners`` into the page
as they were, and a script there ran in the browser. Here markup is put in every string and
every number field of a real result (and in a key of every object): each either is refused with
one line (the document is not a valid result) or is rendered as text, and headless chromium
runs none of it.
"""

from __future__ import annotations

import copy
import json
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path
from typing import Any

import pytest

from calib.result import parse_result
from service.cli.main import main
from service.results.report import render_report
from tests.support.browser import Browser

#: Markup that breaks out of text and of a quoted attribute, each way it could run.
ATTACK = ("\"'><script>window.pwned=1</script><img src=x onerror=\"window.pwned=2\">"
          "<svg onload=window.pwned=3>")
ESCAPED = "&lt;script&gt;window.pwned=1&lt;/script&gt;"

Path_ = tuple[Any, ...]


def leaves(doc: Any, path: Path_ = ()) -> Iterator[tuple[Path_, Any]]:
    """(path, value) of every string, number and boolean in ``doc``, lists read through
    their first two and last items (every station of a list has the same fields; the corner
    arrays hold thousands of numbers of one kind)."""
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from leaves(v, (*path, k))
    elif isinstance(doc, list):
        for i in sorted({*range(min(2, len(doc))), len(doc) - 1} - {-1}):
            yield from leaves(doc[i], (*path, i))
    elif doc is not None:
        yield path, doc


def get(doc: Any, path: Path_) -> Any:
    for key in path:
        doc = doc[key]
    return doc


def put(doc: Any, path: Path_, value: Any) -> None:
    for key in path[:-1]:
        doc = doc[key]
    doc[path[-1]] = value


def objects(doc: Any, path: Path_ = ()) -> Iterator[Path_]:
    """The path of every object in ``doc`` (lists read as in ``leaves``)."""
    if isinstance(doc, dict):
        yield path
        for k, v in doc.items():
            yield from objects(v, (*path, k))
    elif isinstance(doc, list):
        for i in sorted({*range(min(2, len(doc))), len(doc) - 1} - {-1}):
            yield from objects(doc[i], (*path, i))


def refused(doc: dict[str, Any]) -> bool:
    try:
        parse_result(doc)
    except ValueError:
        return True
    return False


def attacked(result: dict[str, Any]) -> tuple[dict[str, Any], int, int]:
    """``result`` with ``ATTACK`` in every field the result schema lets through and as a key
    of every object that takes one; how many fields took it and how many a valid result
    refuses."""
    doc = copy.deepcopy(result)
    taken = refusing = 0
    for path in list(objects(result)):
        obj = get(doc, path)
        for value in (ATTACK, 1.0):  # an attacker's key, with text or a number
            obj[ATTACK] = value
            if not refused(doc):
                break
            del obj[ATTACK]
    for path, _ in list(leaves(result)):
        before = get(doc, path)
        put(doc, path, ATTACK)
        if refused(doc):
            refusing += 1
            put(doc, path, before)
        else:
            taken += 1
    assert not refused(doc)
    return doc, taken, refusing


class _Tags(HTMLParser):
    """Every start tag of a page with its attributes, as a browser's parser sees them."""

    def __init__(self) -> None:
        super().__init__()
        self.tags: list[tuple[str, dict[str, str | None]]] = []

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        self.tags.append((tag, dict(attrs)))


def assert_inert(html: str) -> None:
    """The attack is only text: no script or svg element, no event-handler attribute, every
    image an embedded PNG; and its escaped text is on the page."""
    parser = _Tags()
    parser.feed(html)
    parser.close()
    for tag, attrs in parser.tags:
        assert tag not in ("script", "svg", "iframe", "object", "embed"), (tag, attrs)
        assert not [a for a in attrs if a.startswith("on")], (tag, attrs)
        if tag == "img":
            assert (attrs.get("src") or "").startswith("data:image/png;base64,"), attrs
    assert ESCAPED in html


@pytest.mark.timeout(300)
def test_markup_in_any_field_is_text_or_refused(ur_result, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    _, result = ur_result
    doc, taken, refusing = attacked(result)
    assert taken > 50 and refusing > 50  # both kinds of field are exercised
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(doc))
    out = tmp_path / "edited.html"
    assert main(["report", str(path), "--out", str(out)]) == 0
    html = out.read_text()
    assert_inert(html)
    capsys.readouterr()
    # the two fields of the finding: refused with one line, no page written
    for field in (("camera", "image_size", 0), ("stations", 0, "n_corners")):
        edited = copy.deepcopy(result)
        put(edited, field, ATTACK)
        path.write_text(json.dumps(edited))
        assert main(["report", str(path), "--out", str(tmp_path / "refused.html")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("cellcal: error: ") and err.count("\n") == 1
        assert not (tmp_path / "refused.html").exists()
        with pytest.raises(ValueError):  # and so is the REST report's renderer
            render_report(edited)

    with Browser(tmp_path / "chromium") as browser:
        browser.goto(out.as_uri())
        assert browser.js("typeof window.pwned") == "undefined"
        assert "window.pwned=1" in browser.js("document.body.innerText")
