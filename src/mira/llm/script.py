"""``script:FILE`` — successive calls answered by successive lines of a JSON Lines file.

For tests, demos and teaching: a run can be driven through LSFS and several SRR interventions with
hand-written replies, no network and no rule engine. Each non-blank line is
``{"content": "..."}``, optionally with ``"usage": {"prompt_tokens": N, "completion_tokens": M}``
(so budgets can be exercised). The whole file is validated when the backend is built, so a typo on
line 7 is reported before training starts, not an hour in. The position is checkpointable.
"""

from __future__ import annotations

import hashlib
import json
import time
from pathlib import Path
from typing import Any

from mira.llm.base import LLMReply, LLMRequest, ScriptExhaustedError, ScriptFormatError, TokenUsage


class ScriptBackend:
    """Replies in file order, one per call, whatever the request says."""

    name = "script"

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        try:
            raw = self.path.read_bytes()
        except OSError as exc:
            raise ScriptFormatError(f"cannot read LLM script {self.path}: {exc.strerror or exc}") from exc
        self.model = self.path.name
        self.digest = hashlib.sha256(raw).hexdigest()
        self._entries = _parse(self.path, raw)
        self.position = 0

    def __len__(self) -> int:
        return len(self._entries)

    def complete(self, request: LLMRequest) -> LLMReply:
        if self.position >= len(self._entries):
            raise ScriptExhaustedError(
                f"LLM script {self.path} is exhausted: it holds {len(self._entries)} replies and call "
                f"{self.position + 1} (purpose {request.purpose}) has none"
            )
        started = time.monotonic()
        content, usage = self._entries[self.position]
        self.position += 1
        return LLMReply(
            content=content,
            backend=self.name,
            model=self.model,
            usage=usage,
            latency_s=time.monotonic() - started,
            cached=False,
            attempts=1,
        )

    def state_dict(self) -> dict[str, Any]:
        return {"position": self.position, "sha256": self.digest, "path": str(self.path)}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Resume at a saved position; refuse if the file changed since, which would shift replies."""
        position = int(state["position"])
        if state.get("sha256") not in (None, self.digest):
            raise ScriptFormatError(f"LLM script {self.path} changed since the checkpoint was taken")
        if not 0 <= position <= len(self._entries):
            raise ScriptFormatError(
                f"checkpointed position {position} is outside LLM script {self.path} ({len(self)} replies)"
            )
        self.position = position


def _parse(path: Path, raw: bytes) -> list[tuple[str, TokenUsage]]:
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ScriptFormatError(f"LLM script {path} is not UTF-8 text: {exc}") from exc
    entries: list[tuple[str, TokenUsage]] = []
    for number, line in enumerate(text.splitlines(), start=1):
        if not line.strip():
            continue
        where = f"LLM script {path}, line {number}"
        try:
            obj = json.loads(line)
        except json.JSONDecodeError as exc:
            raise ScriptFormatError(f"{where}: not valid JSON ({exc.msg}, column {exc.colno})") from exc
        if not isinstance(obj, dict) or "content" not in obj:
            raise ScriptFormatError(f'{where}: expected an object like {{"content": "..."}}')
        content = obj["content"]
        if not isinstance(content, str):
            raise ScriptFormatError(f"{where}: 'content' must be a string, not {type(content).__name__}")
        if not content.strip():
            raise ScriptFormatError(f"{where}: 'content' is empty (an empty reply is never a program)")
        usage_obj = obj.get("usage", {})
        if not isinstance(usage_obj, dict) or not all(
            isinstance(usage_obj.get(k, 0), int) and usage_obj.get(k, 0) >= 0
            for k in ("prompt_tokens", "completion_tokens")
        ):
            raise ScriptFormatError(
                f"{where}: 'usage' must map prompt_tokens/completion_tokens to integers >= 0"
            )
        entries.append((content, TokenUsage.from_dict(usage_obj)))
    if not entries:
        raise ScriptFormatError(f"LLM script {path} holds no replies")
    return entries
