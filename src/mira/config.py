"""Typed run configuration. ``config.json`` in a run directory is this dataclass as JSON, and
``--resume`` rebuilds the run from it, so a run directory is enough to rerun a run."""

from __future__ import annotations

import dataclasses
import json
import types
import typing
from dataclasses import dataclass, field
from typing import Any

from mira.agents.base import AgentConfig
from mira.llm.config import LLMConfig
from mira.outer.config import OuterLoopConfig
from mira.shaping.config import HarsConfig


@dataclass
class TrainConfig:
    """Everything that defines a training run."""

    task: str = "halfcheetah"
    """Built-in task name or path to a task card (.toml/.yaml)."""
    method: str = "dense"
    """Reward method: mira, mira-no-mcm, mira-no-srr, hars, dense, sparse, lare, rd, ircr or vib (README)."""
    algo: str = "sac"
    """Off-policy optimiser: ``sac`` or ``ddpg``."""
    steps: int = 100_000
    """Environment steps to train for."""
    seed: int = 0
    """Seed of every random number generator of the run."""
    learning_starts: int = 10_000
    """Uniform-random steps before learning starts."""
    buffer_size: int = 1_000_000
    """Replay capacity (transitions)."""
    eval_every: int = 5_000
    """Evaluate every this many environment steps (and at the end)."""
    eval_episodes: int = 10
    """Deterministic evaluation episodes per evaluation, on a separate environment."""
    checkpoint_every: int = 25_000
    """Checkpoint at the first episode boundary after every this many steps (and at the end)."""
    log_every: int = 1_000
    """Write a ``train.csv`` row every this many steps."""
    max_episode_steps: int | None = None
    """Override the environment's time limit (None: the environment's own, e.g. 1000)."""
    device: str = "auto"
    """``auto`` (CUDA when present), ``cpu`` or ``cuda``."""
    threads: int | None = 1
    """PyTorch intra-op threads of the run. 1 (default): runs that share a machine, as seeds usually do,
    do not slow each other down by oversubscribing its cores, and a run on a free core is about as fast;
    more helps one run alone on an idle machine. None: PyTorch's default (one per core)."""
    agent: AgentConfig = field(default_factory=AgentConfig)
    """Agent hyperparameters."""
    llm: LLMConfig = field(default_factory=LLMConfig)
    """LLM backend settings (methods that use factor programs)."""
    program: str | None = None
    """Start from this factor-program JSON instead of asking the LLM (methods that use programs)."""
    hars: HarsConfig = field(default_factory=HarsConfig)
    """HARS inner-loop shaping (methods with a learned potential)."""
    mira: OuterLoopConfig = field(default_factory=OuterLoopConfig)
    """MIRA's outer loop: monitor (MCM), reframer (SRR) and structural repair (the ablation is the method's)."""


def to_dict(obj: Any) -> Any:
    """A dataclass tree as plain JSON-ready data."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_dict(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, tuple | list):
        return [to_dict(x) for x in obj]
    return obj


def from_dict(cls: type[Any], data: dict[str, Any], where: str = "config") -> Any:
    """Rebuild a dataclass tree; unknown keys are errors that name the key."""
    hints = typing.get_type_hints(cls)
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - known
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {', '.join(sorted(unknown))}")
    kwargs: dict[str, Any] = {}
    for name, value in data.items():
        hint = hints[name]
        if dataclasses.is_dataclass(hint) and isinstance(value, dict):
            kwargs[name] = from_dict(typing.cast(type, hint), value, f"{where}.{name}")
        elif _is_tuple_hint(hint) and isinstance(value, list):
            kwargs[name] = tuple(value)
        else:
            kwargs[name] = value
    return cls(**kwargs)


def drop_removed_fields(data: dict[str, Any], where: str = "config") -> dict[str, Any]:
    """A saved configuration without the fields this version no longer has (:mod:`mira.config_history`).

    A removed field at the value it always had is dropped (the run behaves the same); at any other value
    it is an error naming the field, since this version cannot reproduce that run. Returns a new dict.
    """
    from mira.config_history import REMOVED_FIELDS
    from mira.errors import UsageError

    def walk(node: dict[str, Any], prefix: str) -> dict[str, Any]:
        out: dict[str, Any] = {}
        for key, value in node.items():
            path = f"{prefix}{key}"
            if path in REMOVED_FIELDS:
                if value != REMOVED_FIELDS[path]:
                    raise UsageError(f"{where}: {path} = {value!r}: this setting was removed (it always is "
                                     f"{REMOVED_FIELDS[path]!r} now), so this version cannot reproduce the run")
                continue
            if isinstance(value, dict) and any(name.startswith(f"{path}.") for name in REMOVED_FIELDS):
                value = walk(value, f"{path}.")
                if not value and path in _REMOVED_SECTIONS:
                    continue
            out[key] = value
        return out

    return walk(data, "")


_REMOVED_SECTIONS = frozenset({"baselines", "baselines.lare", "baselines.rd", "baselines.ircr", "baselines.vib"})
"""Sections that went with all their fields."""


def _is_tuple_hint(hint: Any) -> bool:
    origin = typing.get_origin(hint)
    if origin is tuple:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_is_tuple_hint(a) for a in typing.get_args(hint))
    return False


PRESETS: dict[str, tuple[str, ...]] = {
    "paper": ("agent.lr=1e-4", "hars.lr=1e-4", "mira.mcm.delta_t=5000", "mira.repair=false"),
    "paper-letter": ("agent.lr=1e-4", "hars.lr=1e-4", "mira.mcm.delta_t=5000", "mira.repair=false",
                     "hars.alignment=episodic"),
}
"""Named sets of ``--set`` assignments (``mira train --preset NAME``), applied before ``--lr`` and
``--set``. ``paper``: Table 1's learning rate for every network and its monitoring cycle (ΔT = 5,000
steps), and the monitor's anomaly trigger alone (the other Table 1 values are the defaults already).
``paper-letter``: that and section 4.2's Φ, TD-aligned to the episodic reward and added to the agent's
reward with κ = 1, the paper's letter, under which Φ learns only how near an episode's end a state is."""


def apply_override(cfg: Any, assignment: str) -> None:
    """Set a nested field from ``dotted.path=value`` (``--set mira.mcm.delta_t=1000``).

    The value is parsed as JSON when it can be (numbers, true/false, null, lists), else taken as a
    string, and must fit the field's type (null only where the field is optional).
    """
    from mira.errors import UsageError

    path, sep, text = assignment.partition("=")
    if not sep or not path:
        raise UsageError(f"--set {assignment!r}: expected KEY=VALUE, e.g. mira.mcm.delta_t=1000")
    *parents, leaf = path.strip().split(".")
    target = cfg
    for part in parents:
        if not dataclasses.is_dataclass(target) or not hasattr(target, part):
            raise UsageError(f"--set {path}: no section {part!r}")
        target = getattr(target, part)
    if not dataclasses.is_dataclass(target) or leaf not in {f.name for f in dataclasses.fields(target)}:
        raise UsageError(f"--set {path}: no field {leaf!r}")
    current = getattr(target, leaf)
    if dataclasses.is_dataclass(current):
        raise UsageError(f"--set {path}: is a section; set one of its fields")
    try:
        value: Any = json.loads(text)
    except json.JSONDecodeError:
        value = text
    hint_args = typing.get_args(typing.get_type_hints(type(target)).get(leaf, Any))
    if value is None and type(None) in hint_args:  # an optional field may always be set back to null
        ok = True
    elif current is None:  # an optional field now unset: the value must fit its other type
        allowed = tuple(a for a in hint_args if isinstance(a, type) and a is not type(None))
        if float in allowed and isinstance(value, int) and not isinstance(value, bool):
            value = float(value)
        ok = not allowed or (isinstance(value, allowed) and not (isinstance(value, bool) and bool not in allowed))
        if not ok:
            raise UsageError(f"--set {path}={text}: expected {' or '.join(a.__name__ for a in allowed)} or null")
    elif isinstance(current, bool):
        ok = isinstance(value, bool)
    elif isinstance(current, int):
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif isinstance(current, float):
        ok = isinstance(value, int | float) and not isinstance(value, bool)
        value = float(value) if ok else value
    elif isinstance(current, tuple):
        ok = isinstance(value, list)
        value = tuple(value) if ok else value
    elif isinstance(current, str):
        ok, value = True, str(value) if not isinstance(value, str) else value
    else:  # a type without a check here: accept what JSON gave
        ok = True
    if not ok:
        raise UsageError(f"--set {path}={text}: expected a {type(current).__name__} like {current!r}")
    setattr(target, leaf, value)
