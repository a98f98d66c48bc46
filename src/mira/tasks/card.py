"""Task cards: what an LLM (or the offline engineer) is told about a task, and how named state
features are read from observations.

A card is a TOML or YAML file with the Gymnasium environment id, a natural-language description,
the action spec, the evaluation horizon and a list of named features. Each feature is either an
observation index (``index = 8``) or a small arithmetic expression over the observation
(``expr = "1 - 2 * (obs[2] ** 2 + obs[3] ** 2)"``), with units and a one-line meaning. ``source``
optionally names the MuJoCo quantity the feature reads (``qpos:1``, ``qvel:0``), which the test
suite checks against the simulator's own layout.

Feature expressions come from a user's own card, but they are still parsed with a whitelist (numbers,
``obs[i]``, arithmetic, a few NumPy functions) and never passed to ``eval``.
"""

from __future__ import annotations

import ast
import difflib
import importlib
import os
import sys
import tomllib
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from mira.errors import TaskCardError

_CARD_PACKAGE = "mira.tasks.cards"

CARD_KEYS = ("name", "env_id", "description", "features", "action", "eval_horizon", "constraints", "env_kwargs",
             "band_feature")
"""Keys a card may have at its top level (docs/task_cards.md explains each)."""
ACTION_KEYS = ("doc", "names")
FEATURE_KEYS = ("name", "index", "expr", "units", "doc", "source", "better", "target", "range")
BETTER = ("higher", "lower", "closer")
"""What a feature's ``better`` key may say: larger values are better, smaller are, or nearer ``target``."""

_EXPR_FUNCS: dict[str, Callable[..., np.ndarray]] = {
    "abs": np.abs,
    "sqrt": np.sqrt,
    "sin": np.sin,
    "cos": np.cos,
    "tanh": np.tanh,
    "arctan2": np.arctan2,
    "arcsin": np.arcsin,
    "arccos": np.arccos,
    "clip": np.clip,
    "minimum": np.minimum,
    "maximum": np.maximum,
}


@dataclass(frozen=True)
class Feature:
    """One named, documented quantity of the state."""

    name: str
    units: str
    doc: str
    index: int | None = None
    expr: str | None = None
    source: str | None = None
    better: str | None = None
    """What the task prefers: ``higher``, ``lower`` or ``closer`` (to ``target``); None: not declared."""
    target: float | None = None
    """With ``better = "closer"``: the preferred value (0 when omitted)."""
    range: tuple[float, float] | None = None
    """The values it takes while an episode runs (termination thresholds included), when declared: the
    sandbox checks divisions, logarithms and roots of the feature over it."""

    def describe(self) -> str:
        where = f"obs[{self.index}]" if self.index is not None else str(self.expr)
        pref = ""
        if self.better is not None:
            pref = f"  (better: {self.better}" + (f" to {self.target:g}" if self.better == "closer" else "") + ")"
        return f"s.{self.name}  [{self.units}]  {self.doc}  (= {where}){pref}"


class _ExprCompiler:
    """Compile a feature expression to a function of the observation batch ``[B, obs_dim]``."""

    def __init__(self, feature: str, obs_dim: int | None) -> None:
        self.feature = feature
        self.obs_dim = obs_dim
        self.indices: list[int] = []

    def compile(self, text: str) -> Callable[[np.ndarray], np.ndarray]:
        try:
            tree = ast.parse(text, mode="eval")
        except SyntaxError as exc:
            raise TaskCardError(f"feature {self.feature!r}: expression {text!r} does not parse: {exc.msg}") from exc
        return self._node(tree.body)

    def _fail(self, node: ast.AST, why: str) -> TaskCardError:
        return TaskCardError(f"feature {self.feature!r}: {why} (column {getattr(node, 'col_offset', 0) + 1})")

    def _node(self, node: ast.AST) -> Callable[[np.ndarray], np.ndarray]:
        if isinstance(node, ast.Constant) and isinstance(node.value, int | float) and not isinstance(
            node.value, bool
        ):
            value = float(node.value)
            return lambda obs: np.full(obs.shape[0], value, dtype=obs.dtype)
        if isinstance(node, ast.Subscript) and isinstance(node.value, ast.Name) and node.value.id == "obs":
            if not (isinstance(node.slice, ast.Constant) and type(node.slice.value) is int):
                raise self._fail(node, "obs must be indexed by an integer constant")
            idx = node.slice.value
            if idx < 0 or (self.obs_dim is not None and idx >= self.obs_dim):
                raise self._fail(node, f"index {idx} is outside the observation (size {self.obs_dim})")
            self.indices.append(idx)
            return lambda obs: obs[:, idx]
        if isinstance(node, ast.UnaryOp) and isinstance(node.op, ast.USub | ast.UAdd):
            inner = self._node(node.operand)
            sign = -1.0 if isinstance(node.op, ast.USub) else 1.0
            return lambda obs: sign * inner(obs)
        if isinstance(node, ast.BinOp):
            ops: dict[type, Callable[[Any, Any], Any]] = {
                ast.Add: np.add,
                ast.Sub: np.subtract,
                ast.Mult: np.multiply,
                ast.Div: np.divide,
                ast.Pow: np.power,
            }
            op = ops.get(type(node.op))
            if op is None:
                raise self._fail(node, f"operator {type(node.op).__name__} is not allowed")
            if isinstance(node.op, ast.Pow) and not (
                isinstance(node.right, ast.Constant) and isinstance(node.right.value, int | float)
                and abs(node.right.value) <= 4
            ):
                raise self._fail(node, "powers must have a small constant exponent")
            left, right = self._node(node.left), self._node(node.right)
            return lambda obs: op(left(obs), right(obs))
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and not node.keywords:
            fn = _EXPR_FUNCS.get(node.func.id)
            if fn is None:
                raise self._fail(node, f"function {node.func.id!r} is not allowed (allowed: {sorted(_EXPR_FUNCS)})")
            args = [self._node(a) for a in node.args]
            return lambda obs: fn(*(a(obs) for a in args))
        raise self._fail(node, f"{type(node).__name__} is not allowed in a feature expression")


class StateView:
    """Read-only, vectorised view of a batch of states: one attribute per named feature (``[B]``)
    and ``obs`` (``[B, obs_dim]``)."""

    __slots__ = ("_values",)

    def __init__(self, values: dict[str, np.ndarray]) -> None:
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name: str) -> np.ndarray:
        values = object.__getattribute__(self, "_values")
        try:
            return values[name]
        except KeyError:
            raise AttributeError(f"the state has no feature {name!r}") from None

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("the state view is read-only")

    def names(self) -> list[str]:
        return list(object.__getattribute__(self, "_values"))


@dataclass
class TaskCard:
    """A Gymnasium environment plus what a reward engineer needs to know about it."""

    name: str
    env_id: str
    description: str
    features: tuple[Feature, ...]
    action_doc: str
    eval_horizon: int = 1000
    action_names: tuple[str, ...] = ()
    constraints: tuple[str, ...] = ()
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    source_path: str | None = None
    band_feature: str | None = None
    """The feature whose held-out values locate a stagnation band (section 4.4.2's escape bonus), e.g.
    the torso height of a stand-up task; None: the monitor reports no band."""

    def __post_init__(self) -> None:
        self._compiled: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
        self._obs_dim: int | None = None

    @property
    def feature_names(self) -> list[str]:
        return [f.name for f in self.features]

    @property
    def where(self) -> str:
        """How errors name this card: its file when it came from one, else its name."""
        return self.source_path or repr(self.name)

    def bind(self, obs_dim: int) -> None:
        """Check every feature against an observation of ``obs_dim`` entries and compile it."""
        compiled: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
        for i, feat in enumerate(self.features):
            if feat.index is not None:
                if not 0 <= feat.index < obs_dim:
                    raise TaskCardError(
                        f"task card {self.where}, features[{i}] ({feat.name!r}): reads obs[{feat.index}], but "
                        f"{self.env_id} observations have {obs_dim} entries (obs[0] to obs[{obs_dim - 1}])"
                    )
                compiled[feat.name] = _column(feat.index)
            else:
                assert feat.expr is not None
                try:
                    compiled[feat.name] = _ExprCompiler(feat.name, obs_dim).compile(feat.expr)
                except TaskCardError as exc:
                    raise TaskCardError(f"task card {self.where}, features[{i}]: {exc}") from None
        self._compiled = compiled
        self._obs_dim = obs_dim

    @property
    def obs_dim(self) -> int:
        if self._obs_dim is None:
            raise RuntimeError(f"task card {self.name!r} is not bound to an environment yet")
        return self._obs_dim

    def feature_values(self, obs: np.ndarray) -> dict[str, np.ndarray]:
        """Every named feature of a batch of observations ``[B, obs_dim]`` as float64 ``[B]`` arrays."""
        if not self._compiled:
            self.bind(obs.shape[-1])
        batch = np.asarray(obs, dtype=np.float64)
        if batch.ndim == 1:
            batch = batch[None, :]
        return {name: np.ascontiguousarray(fn(batch), dtype=np.float64) for name, fn in self._compiled.items()}

    def state_view(self, obs: np.ndarray) -> StateView:
        """A read-only :class:`StateView` of a batch of observations."""
        batch = np.array(obs, dtype=np.float64, ndmin=2)
        values = self.feature_values(batch)
        values["obs"] = batch
        for arr in values.values():
            arr.setflags(write=False)
        return StateView(values)

    def spec_text(self, action_dim: int | None = None) -> tuple[str, str]:
        """Human- and LLM-readable state and action specifications."""
        state = "\n".join(f"- {f.describe()}" for f in self.features)
        if self._obs_dim is not None:
            state += f"\n- s.obs  [mixed]  the raw observation vector, shape [B, {self._obs_dim}]"
        action = self.action_doc.strip()
        if action_dim is not None:
            action += f"\n(a has shape [B, {action_dim}], each entry in [-1, 1] after scaling)"
        return state, action


def _column(idx: int) -> Callable[[np.ndarray], np.ndarray]:
    return lambda obs: obs[:, idx]


def builtin_task_names() -> list[str]:
    """Names of the cards shipped with MIRA."""
    return sorted(p.name[: -len(".toml")] for p in resources.files(_CARD_PACKAGE).iterdir() if p.name.endswith(".toml"))


def _check_keys(data: dict[str, Any], allowed: tuple[str, ...], where: str) -> None:
    """An unknown key is an error naming the nearest valid one: a typo must not be ignored silently."""
    for key in data:
        if key not in allowed:
            near = difflib.get_close_matches(str(key), allowed, n=1)
            hint = f"; did you mean {near[0]!r}?" if near else f" (valid keys: {', '.join(allowed)})"
            raise TaskCardError(f"task card {where}: unknown key {key!r}{hint}")


def _require(data: dict[str, Any], key: str, where: str, kind: type | tuple[type, ...]) -> Any:
    if key not in data:
        raise TaskCardError(f"task card {where}: missing required field {key!r}")
    value = data[key]
    if not isinstance(value, kind):
        raise TaskCardError(f"task card {where}: field {key!r} has the wrong type ({type(value).__name__})")
    return value


def card_from_dict(data: dict[str, Any], where: str) -> TaskCard:
    """Build and validate a card from parsed TOML/YAML; ``where`` names it in error messages."""
    if not isinstance(data, dict):
        raise TaskCardError(f"task card {where}: expected a table/mapping at the top level")
    _check_keys(data, CARD_KEYS, where)
    name = _require(data, "name", where, str)
    env_id = _require(data, "env_id", where, str)
    description = _require(data, "description", where, str)
    raw_features = _require(data, "features", where, list)
    action = _require(data, "action", where, dict)
    _check_keys(action, ACTION_KEYS, f"{where}, action")
    names = action.get("names", [])
    if not isinstance(names, list) or not all(isinstance(n, str) and n for n in names):
        raise TaskCardError(f"task card {where}, action: key 'names' must be a list of non-empty strings")
    features: list[Feature] = []
    seen: set[str] = set()
    for i, raw in enumerate(raw_features):
        at = f"{where}, features[{i}]"
        if not isinstance(raw, dict):
            raise TaskCardError(f"task card {at}: expected a table")
        _check_keys(raw, FEATURE_KEYS, at)
        fname = _require(raw, "name", at, str)
        if not fname.isidentifier() or fname.startswith("_") or fname == "obs":
            raise TaskCardError(f"task card {at}: feature name {fname!r} is not a valid identifier")
        if fname in seen:
            raise TaskCardError(f"task card {at}: duplicate feature {fname!r}")
        seen.add(fname)
        index, expr = raw.get("index"), raw.get("expr")
        if (index is None) == (expr is None):
            raise TaskCardError(f"task card {at}: feature {fname!r} needs exactly one of 'index' or 'expr'")
        if index is not None and (type(index) is not int or index < 0):
            raise TaskCardError(f"task card {at}: feature {fname!r} has a bad index {index!r}")
        if expr is not None:
            if not isinstance(expr, str):
                raise TaskCardError(f"task card {at}: feature {fname!r} expr must be a string")
            _ExprCompiler(fname, None).compile(expr)  # syntax and whitelist now; bounds once bound
        better, target = raw.get("better"), raw.get("target")
        if better is not None and better not in BETTER:
            raise TaskCardError(f"task card {at}: feature {fname!r} key 'better' must be one of {', '.join(BETTER)}, "
                                f"not {better!r}")
        if target is not None and (better != "closer" or type(target) not in (int, float)):
            raise TaskCardError(f"task card {at}: feature {fname!r} key 'target' must be a number, and only with "
                                "better = \"closer\"")
        declared = raw.get("range")
        if declared is not None and not (isinstance(declared, list) and len(declared) == 2
                                         and all(type(v) in (int, float) for v in declared)
                                         and declared[0] <= declared[1]):
            raise TaskCardError(f"task card {at}: feature {fname!r} key 'range' must be [lo, hi] with lo <= hi, "
                                f"not {declared!r}")
        features.append(
            Feature(
                name=fname,
                units=str(raw.get("units", "")),
                doc=str(raw.get("doc", "")),
                index=index,
                expr=expr,
                source=raw.get("source"),
                better=better,
                target=None if better != "closer" else float(target or 0.0),
                range=None if declared is None else (float(declared[0]), float(declared[1])),
            )
        )
    if not features:
        raise TaskCardError(f"task card {where}: it declares no features")
    horizon = data.get("eval_horizon", 1000)
    if type(horizon) is not int or horizon <= 0:
        raise TaskCardError(f"task card {where}: eval_horizon must be a positive integer")
    band = data.get("band_feature")
    if band is not None and band not in {f.name for f in features}:
        raise TaskCardError(f"task card {where}: band_feature {band!r} is not one of its features")
    return TaskCard(
        name=name,
        env_id=env_id,
        description=description.strip(),
        features=tuple(features),
        action_doc=str(action.get("doc", "")),
        action_names=tuple(action.get("names", ())),
        eval_horizon=horizon,
        constraints=tuple(data.get("constraints", ())),
        env_kwargs=dict(data.get("env_kwargs", {})),
        band_feature=band,
    )


def _parse_file(path: Path) -> dict[str, Any]:
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise TaskCardError(f"task card {path}: cannot read it ({exc.strerror})") from exc
    if not text.strip():
        raise TaskCardError(f"task card {path}: the file is empty (docs/task_cards.md has a complete example)")
    try:
        if path.suffix == ".toml":
            return tomllib.loads(text)
        data = yaml.safe_load(text)
    except tomllib.TOMLDecodeError as exc:
        # tomllib's message ends with "(at line L, column C)".
        raise TaskCardError(f"task card {path}: does not parse as TOML: {exc}") from exc
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" (at line {mark.line + 1}, column {mark.column + 1})" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise TaskCardError(f"task card {path}: does not parse as YAML: {problem}{at}") from exc
    if not isinstance(data, dict):
        raise TaskCardError(f"task card {path}: expected a mapping at the top level, got {type(data).__name__}")
    return data


def load_task(name_or_path: str, check_env: bool = True) -> TaskCard:
    """A built-in card by name, or a user's ``.toml``/``.yaml`` card by path.

    With ``check_env`` the environment id must be registered with Gymnasium.
    """
    builtin = builtin_task_names()
    if name_or_path in builtin:
        text = resources.files(_CARD_PACKAGE).joinpath(f"{name_or_path}.toml").read_text(encoding="utf-8")
        card = card_from_dict(tomllib.loads(text), name_or_path)
    else:
        path = Path(name_or_path)
        if path.suffix not in (".toml", ".yaml", ".yml"):
            raise TaskCardError(
                f"unknown task {name_or_path!r}: use one of {', '.join(builtin)} or a path to a .toml/.yaml card"
            )
        if not path.is_file():
            raise TaskCardError(f"task card {path}: no such file")
        card = card_from_dict(_parse_file(path), str(path))
        card.source_path = str(path.resolve())
    if check_env:
        _check_env_registered(card)
    return card


def import_env_module(env_id: str, card_path: str | None = None) -> str:
    """The Gymnasium id of ``env_id``, having imported its module first when it is written
    ``"module:Env-v0"`` (as ``gymnasium.make`` accepts it: the module registers the environment when
    imported).

    The module is imported as Python finds it (installed, or on ``PYTHONPATH``); failing that, from the
    directory of the card that names it (``card_path``), then from the current directory, which are
    added to ``sys.path`` for the rest of the process.
    """
    module, sep, name = env_id.partition(":")
    if not sep:
        return env_id
    if not module or not name:
        raise TaskCardError(f"environment {env_id!r}: expected module:Env-v0")
    try:
        importlib.import_module(module)
    except ModuleNotFoundError as exc:
        if exc.name != module.split(".")[0] and exc.name != module:
            raise TaskCardError(f"environment {env_id!r}: importing {module!r} failed: {exc}") from exc
        places = [str(Path(card_path).resolve().parent)] if card_path else []
        places.append(os.getcwd())
        for place in places:
            if place not in sys.path:
                sys.path.append(place)
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as again:
            raise TaskCardError(
                f"environment {env_id!r}: no module {module!r} (looked on sys.path, then in "
                f"{' and '.join(places)}); install it or put it on PYTHONPATH") from again
    except Exception as exc:  # the user's module itself fails: say so, with its error
        raise TaskCardError(f"environment {env_id!r}: importing {module!r} failed: "
                            f"{type(exc).__name__}: {exc}") from exc
    return name


def _check_env_registered(card: TaskCard) -> None:
    import gymnasium

    env_id = import_env_module(card.env_id, card.source_path)
    try:
        gymnasium.spec(env_id)
    except gymnasium.error.Error as exc:
        where = f" (module {card.env_id.partition(':')[0]!r} was imported but did not register it)" \
            if env_id != card.env_id else ""
        raise TaskCardError(
            f"task card {card.name!r}: environment {env_id!r} is not registered with Gymnasium{where} ({exc})"
        ) from exc


def card_to_dict(card: TaskCard) -> dict[str, Any]:
    """The card as plain data (saved into every run directory)."""
    feats: Iterable[dict[str, Any]] = (
        {k: v for k, v in vars(f).items() if v is not None} for f in card.features
    )
    return {
        "name": card.name,
        "env_id": card.env_id,
        "description": card.description,
        "eval_horizon": card.eval_horizon,
        "constraints": list(card.constraints),
        "env_kwargs": card.env_kwargs,
        "band_feature": card.band_feature,
        "action": {"doc": card.action_doc, "names": list(card.action_names)},
        "features": list(feats),
    }
