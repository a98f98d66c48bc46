"""The JSON object in a model's reply, read the way models write it.

Models wrap the object in a code fence, put prose around it, and write ``"code"`` strings with
literal newlines or tabs instead of ``\\n``; none of that changes what they meant, so all of it is
read (control characters inside strings are accepted: JSON's ``strict=False``). What cannot be read
is reported at its place in the *reply* (line and column of the whole text, not of the fence's
content) with that line's text, so the model, or a person, can find it.
"""

from __future__ import annotations

import json
import re
from typing import Any

from mira.factors.program import ProgramParseError

_FENCE = re.compile(r"```[ \t]*(?:json|JSON|javascript|js)?[ \t]*\r?\n(.*?)```", re.DOTALL)
_DECODER = json.JSONDecoder(strict=False)
MAX_STARTS = 200
"""Opening braces tried in prose before giving up (a reply of text with braces, never JSON)."""


def _where(text: str, pos: int) -> str:
    line = text.count("\n", 0, pos) + 1
    start = text.rfind("\n", 0, pos) + 1
    end = text.find("\n", pos)
    snippet = text[start: end if end != -1 else len(text)].strip()
    if len(snippet) > 100:
        snippet = snippet[:97] + "..."
    return f"line {line} column {pos - start + 1} of the reply" + (f" (`{snippet}`)" if snippet else "")


def find_json_object(text: str, key: str) -> dict[str, Any]:
    """The first JSON object in ``text`` that has ``key``: the whole text, a fenced block, or an object
    embedded in prose. Raises :class:`ProgramParseError` naming the first decoding error's place."""
    first_error: str | None = None
    spans: list[tuple[int, int]] = []
    stripped = text.strip()
    if stripped:
        spans.append((text.find(stripped), text.find(stripped) + len(stripped)))
    spans += [(m.start(1), m.end(1)) for m in _FENCE.finditer(text)]
    for start, end in spans:
        chunk = text[start:end]
        lead = len(chunk) - len(chunk.lstrip())
        try:
            value, _ = _DECODER.raw_decode(chunk, lead)
        except json.JSONDecodeError as exc:
            if chunk.lstrip().startswith("{") and first_error is None:
                first_error = f"{exc.msg} at {_where(text, start + exc.pos)}"
            continue
        except RecursionError:
            first_error = first_error or "the JSON is nested too deeply"
            continue
        if isinstance(value, dict) and key in value:  # prose after a complete object does not change it
            return value
    # Objects embedded in prose: never look inside an object that decoded.
    pos, tries = text.find("{"), 0
    while pos >= 0 and tries < MAX_STARTS:
        tries += 1
        try:
            value, end = _DECODER.raw_decode(text, pos)
        except json.JSONDecodeError as exc:
            if first_error is None and f'"{key}"' in text[pos:pos + 2000]:
                first_error = f"{exc.msg} at {_where(text, exc.pos)}"
            pos = text.find("{", pos + 1)
            continue
        except RecursionError:
            pos = text.find("{", pos + 1)
            continue
        if isinstance(value, dict) and key in value:
            return value
        pos = text.find("{", end)
    if first_error is not None:
        raise ProgramParseError(f"the reply is not valid JSON: {first_error}")
    raise ProgramParseError(f"the reply has no JSON object with a {key!r} key")
