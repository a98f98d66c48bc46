"""``offline`` — the default reward engineer: deterministic rules, no network, and no pretence.

MIRA must run out of the box on a machine without an API key, and its tests and case studies must
be reproducible bit for bit; so the default engineer is a rule engine that answers from the
structured facts in ``request.context`` (it cannot read the prose of the messages). It says what it
is everywhere: ``name`` "offline", ``model`` "rule-based-engineer-v2", and an ``"engineer"`` field
in every reply stating it is a rule-based engineer, not an LLM.

* ``lsfs`` (and ``lare``, which asks for the same kind of factor program): see ``offline_lsfs``.
* ``srr``: the evidence-to-operator rules of section 4.4.2, see ``offline_srr``.

Replies are JSON with a fixed key order and indentation, so the same context gives byte-identical
content.
"""

from __future__ import annotations

import json
import time
from typing import Any

from mira.engineer.offline_lsfs import synthesize
from mira.engineer.offline_srr import propose
from mira.llm.base import LLMReply, LLMRequest, LLMRequestRejectedError

OFFLINE_MODEL = "rule-based-engineer-v2"


class OfflineEngineer:
    """Rule-based stand-in for the LLM, for LSFS and SRR requests that carry a ``context``."""

    name = "offline"
    model = OFFLINE_MODEL

    def answer(self, request: LLMRequest) -> dict[str, Any]:
        """The reply as a JSON object (before serialisation)."""
        context = request.context
        if not isinstance(context, dict) or not context:
            raise LLMRequestRejectedError(
                f"offline engineer: a {request.purpose} request needs request.context (the structured facts "
                "the prompt was built from); it cannot read the prose of the messages"
            )
        if request.purpose in ("lsfs", "lare"):
            return synthesize(context)
        return propose(context)

    def complete(self, request: LLMRequest) -> LLMReply:
        started = time.monotonic()
        content = json.dumps(self.answer(request), indent=2, ensure_ascii=False, allow_nan=False)
        return LLMReply(
            content=content + "\n",
            backend=self.name,
            model=self.model,
            latency_s=time.monotonic() - started,
            cached=False,
            attempts=1,
            finish_reason="stop",
        )
