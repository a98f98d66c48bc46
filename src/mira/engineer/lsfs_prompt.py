"""Linguistic–Semantic Factor Synthesis (section 4.2.1): the prompt, and a strict reader of the reply.

The prompt follows the paper's structured chain of thought: role and context priming (system
message; task, state and action specification from the task card), hierarchical decomposition
into sub-goals, factor identification per sub-goal with a PHI/AUX type, and code in the restricted
factor language with a strict JSON output format. The templates live in ``prompts/*.txt`` and are
filled with :class:`string.Template` (``$name`` placeholders), so card text is inserted verbatim and
never interpreted.

The reply reader accepts what real chat models send: the JSON alone, the JSON inside a
```` ```json ```` fence, or prose around it; ``code`` given as a list of lines; a lower-case type tag.
Anything else (no object with a ``factors`` list, invalid JSON, trailing commas, fields of the wrong
type, duplicate names, PHI code that reads the action) is a :class:`ProgramParseError` with a
message that says what was wrong. Parsing is not admission: the result still goes through the
static checker and the sandbox.
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from importlib import resources
from string import Template
from typing import TYPE_CHECKING, Any

from mira.engineer.replyjson import find_json_object
from mira.factors.program import FACTOR_FIELDS, Factor, FactorProgram, ProgramParseError
from mira.factors.whitelist import allowed_syntax_summary

if TYPE_CHECKING:
    from mira.tasks.card import TaskCard

MAX_REPLY_CHARS = 200_000
FACTOR_USAGE = (
    "The environment pays its reward only once, at the end of an episode (the sum of what it would have "
    "paid per step). The learning system fits a per-step reward r(s, a, s') = sum_i w_i * f_i + b to the "
    "episodes' returns: PHI factors read at the next state s', AUX factors at (s, a), the weights refitted "
    "by regression after every episode, and the agent learns from that r. So each factor's sign and scale "
    "are learned from the returns: what matters is which quantities the program reads, each in a form "
    "(value, square, gated, saturated) whose weighted sum can express what the task pays for. A potential "
    "over the PHI factors is also learned and watched by a monitor (and, if configured, added as "
    "potential-based shaping)."
)
"""How MIRA uses a program, said in both prompts so a model writes factors for the use they get."""


def example_factor(card: TaskCard) -> str:
    """The format of one factor, over this task's first feature: an example that names fields the task
    does not have invites the model to read them. It shows the form only, not a choice of factor."""
    feature = card.features[0]
    name = f"f_{feature.name}"
    return json.dumps({"name": name, "type": "PHI", "code": f"def {name}(s):\n    return np.tanh(s.{feature.name})\n",
                       "doc": feature.doc or feature.name, "units": feature.units or "1", "range_hint": "[-1, 1]"})


def _template(name: str) -> Template:
    return Template(resources.files("mira.engineer").joinpath("prompts", name).read_text(encoding="utf-8"))


def build_lsfs_messages(
    card: TaskCard, action_dim: int | None = None, *, min_factors: int = 3, max_factors: int = 6
) -> list[dict[str, str]]:
    """OpenAI-style chat messages (system + user) asking for the initial factor program of a task."""
    state_spec, action_spec = card.spec_text(action_dim)
    constraints = "\n".join(f"- {c}" for c in card.constraints) or "- (none beyond the factor language)"
    constraints += (
        "\n- No dependence on the next state or on anything but the current state (and action for AUX)."
    )
    user = _template("lsfs_user.txt").substitute(
        task_name=card.name,
        task_description=card.description.strip(),
        state_spec=state_spec,
        action_spec=action_spec,
        action_dim=str(action_dim) if action_dim is not None else "act_dim",
        constraints=constraints,
        min_factors=str(min_factors),
        max_factors=str(max_factors),
        syntax=allowed_syntax_summary(),
        example_factor=example_factor(card),
        usage=FACTOR_USAGE,
    )
    system = _template("lsfs_system.txt").substitute()
    return [{"role": "system", "content": system.strip()}, {"role": "user", "content": user.strip()}]


def _normalise_factor(raw: Any, index: int) -> dict[str, Any]:
    where = f"factors[{index}]"
    if not isinstance(raw, Mapping):
        raise ProgramParseError(f"{where}: expected an object, got {type(raw).__name__}")
    data = {k: raw[k] for k in FACTOR_FIELDS if k in raw}
    code = data.get("code")
    if isinstance(code, list) and all(isinstance(line, str) for line in code):
        data["code"] = "\n".join(line.rstrip("\n") for line in code)
    if isinstance(data.get("code"), str) and not data["code"].endswith("\n"):
        data["code"] += "\n"
    if isinstance(data.get("type"), str):
        data["type"] = data["type"].strip().upper()
    return data


def parse_program_reply(
    text: str, card: TaskCard | None = None, task_name: str | None = None
) -> FactorProgram:
    """The factor program in an LLM reply, as version 0 of ``task_name`` (default: the card's name)."""
    if not isinstance(text, str) or not text.strip():
        raise ProgramParseError("the reply is empty")
    if len(text) > MAX_REPLY_CHARS:
        raise ProgramParseError(
            f"the reply is {len(text)} characters long; at most {MAX_REPLY_CHARS} are read"
        )
    task = task_name or (card.name if card is not None else None)
    if not task:
        raise ProgramParseError("no task name given for the program")
    obj = find_json_object(text, "factors")
    raw_factors = obj["factors"]
    if not isinstance(raw_factors, list) or not raw_factors:
        raise ProgramParseError("'factors' must be a non-empty list of factor objects")
    factors = tuple(
        Factor.from_json(_normalise_factor(f, i), f"factors[{i}]") for i, f in enumerate(raw_factors)
    )
    parts: list[str] = []
    subgoals = obj.get("subgoals")
    if isinstance(subgoals, list) and all(isinstance(g, str) for g in subgoals):
        parts.append("Sub-goals: " + "; ".join(subgoals))
    if isinstance(obj.get("rationale"), str):
        parts.append(obj["rationale"])
    return FactorProgram(task=task, version=0, factors=factors, rationale="\n".join(parts))
