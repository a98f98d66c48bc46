"""What HARS needs from a factor program, and running statistics of factor values.

HARS is decoupled from how factors are written and checked: it talks to a :class:`FactorSource`,
a small protocol that evaluates the state-only (PHI) factors on a batch of raw observations and the
state–action (AUX) factors on observations and actions. :class:`ProgramFactorSource` adapts an
admitted :class:`mira.factors.program.FactorProgram` (compiled by :mod:`mira.factors.evaluator`);
:class:`FunctionFactorSource` wraps plain NumPy callables (tests, notebooks, hand-written factors).

Factor metadata (``meta_i`` of the FAB, section 4.2.2) is the declared range and polarity of each
PHI factor plus its running normalisation statistics (:class:`RunningStats`), turned into a fixed-
length vector by :func:`meta_features`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

if TYPE_CHECKING:
    from mira.factors.program import FactorProgram
    from mira.tasks.card import TaskCard

POLARITY_SIGN = {"reward": 1.0, "penalty": -1.0, "mixed": 0.0}

META_DIM = 8
"""Length of a factor's metadata vector: [polarity +, polarity −, lo finite, symlog lo, hi finite,
symlog hi, symlog running mean, symlog running std]."""


@dataclass(frozen=True)
class FactorMeta:
    """Declared facts about one PHI factor (all optional)."""

    range_lo: float | None = None
    range_hi: float | None = None
    polarity: str | None = None
    units: str = ""


@runtime_checkable
class FactorSource(Protocol):
    """A factor program as HARS sees it.

    ``phi(obs)`` maps raw observations ``[B, obs_dim]`` to the PHI factors ``[B, K_phi]`` in the
    order of ``phi_names``; ``aux(obs, act)`` gives the AUX factors ``[B, K_aux]``. Both return
    finite float arrays. ``meta`` maps each PHI name to its :class:`FactorMeta`.

    A source may also offer ``transition(obs, next_obs, act) -> (phi_s, phi_next, aux | None)`` for
    one transition (1-D arrays); HARS uses it per stored step when present.
    """

    @property
    def phi_names(self) -> list[str]: ...

    @property
    def aux_names(self) -> list[str]: ...

    @property
    def meta(self) -> Mapping[str, FactorMeta]: ...

    def phi(self, obs: np.ndarray) -> np.ndarray: ...

    def aux(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray: ...


def range_bounds(text: str | None) -> tuple[float | None, float | None]:
    """A program's ``range_hint`` (``"[-15, 15]"``, ``"(-inf, 0]"``) as (lo, hi); None for no bound."""
    from mira.factors.checker import parse_range_hint

    parsed = parse_range_hint(text) if text else None
    if parsed is None:
        return None, None
    lo, hi = parsed
    return (lo if math.isfinite(lo) else None), (hi if math.isfinite(hi) else None)


def _symlog(x: np.ndarray) -> np.ndarray:
    return np.sign(x) * np.log1p(np.abs(x))


def meta_features(names: Sequence[str], meta: Mapping[str, FactorMeta], mean: np.ndarray,
                  std: np.ndarray) -> np.ndarray:
    """The ``[K, META_DIM]`` metadata matrix of the FAB (float32)."""
    k = len(names)
    out = np.zeros((k, META_DIM), dtype=np.float64)
    for j, name in enumerate(names):
        m = meta.get(name, FactorMeta())
        sign = POLARITY_SIGN.get(m.polarity or "", 0.0)
        out[j, 0] = max(sign, 0.0)
        out[j, 1] = max(-sign, 0.0)
        if m.range_lo is not None:
            out[j, 2], out[j, 3] = 1.0, m.range_lo
        if m.range_hi is not None:
            out[j, 4], out[j, 5] = 1.0, m.range_hi
    out[:, 3] = _symlog(out[:, 3])
    out[:, 5] = _symlog(out[:, 5])
    out[:, 6] = _symlog(np.asarray(mean, dtype=np.float64))
    out[:, 7] = _symlog(np.asarray(std, dtype=np.float64))
    return out.astype(np.float32)


class RunningStats:
    """Per-column running mean and variance (Welford / Chan et al.'s parallel update), float64."""

    def __init__(self, dim: int) -> None:
        self.count = 0
        self.mean = np.zeros(dim, dtype=np.float64)
        self.m2 = np.zeros(dim, dtype=np.float64)

    @property
    def dim(self) -> int:
        return int(self.mean.shape[0])

    def update(self, x: np.ndarray) -> None:
        """Fold a batch ``[N, dim]`` (or one row ``[dim]``) into the statistics."""
        x = np.asarray(x, dtype=np.float64)
        if x.ndim == 1:
            x = x[None, :]
        n = x.shape[0]
        if n == 0:
            return
        if n == 1:  # Welford's single-sample update (the per-transition hot path)
            self.count += 1
            delta = x[0] - self.mean
            self.mean += delta / self.count
            self.m2 += delta * (x[0] - self.mean)
            return
        b_mean = x.mean(axis=0)
        b_m2 = ((x - b_mean) ** 2).sum(axis=0)
        total = self.count + n
        delta = b_mean - self.mean
        self.mean = self.mean + delta * (n / total)
        self.m2 = self.m2 + b_m2 + delta**2 * (self.count * n / total)
        self.count = total

    @property
    def var(self) -> np.ndarray:
        if self.count < 2:
            return np.ones_like(self.mean) if self.count == 0 else np.zeros_like(self.mean)
        return self.m2 / self.count

    @property
    def std(self) -> np.ndarray:
        return np.sqrt(self.var)

    def select(self, columns: Sequence[int]) -> RunningStats:
        out = RunningStats(len(columns))
        out.count = self.count
        out.mean = self.mean[list(columns)].copy()
        out.m2 = self.m2[list(columns)].copy()
        return out

    def state_dict(self) -> dict[str, Any]:
        return {"count": self.count, "mean": self.mean.copy(), "m2": self.m2.copy()}

    def load_state_dict(self, state: Mapping[str, Any]) -> None:
        self.count = int(state["count"])
        self.mean = np.array(state["mean"], dtype=np.float64)
        self.m2 = np.array(state["m2"], dtype=np.float64)


class FunctionFactorSource:
    """Factors given as NumPy callables: PHI ``fn(obs [B, D]) -> [B]``, AUX ``fn(obs, act) -> [B]``."""

    def __init__(
        self,
        phi: Mapping[str, Callable[[np.ndarray], np.ndarray]],
        aux: Mapping[str, Callable[[np.ndarray, np.ndarray], np.ndarray]] | None = None,
        meta: Mapping[str, FactorMeta] | None = None,
    ) -> None:
        self._phi = dict(phi)
        self._aux = dict(aux or {})
        self._meta = {name: (meta or {}).get(name, FactorMeta()) for name in self._phi}

    @property
    def phi_names(self) -> list[str]:
        return list(self._phi)

    @property
    def aux_names(self) -> list[str]:
        return list(self._aux)

    @property
    def meta(self) -> Mapping[str, FactorMeta]:
        return self._meta

    def phi(self, obs: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        out = np.empty((obs.shape[0], len(self._phi)), dtype=np.float64)
        for j, fn in enumerate(self._phi.values()):
            out[:, j] = fn(obs)
        return out

    def aux(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        obs = np.asarray(obs, dtype=np.float64)
        out = np.empty((obs.shape[0], len(self._aux)), dtype=np.float64)
        for j, fn in enumerate(self._aux.values()):
            out[:, j] = fn(obs, np.asarray(act, dtype=np.float64))
        return out


class ProgramFactorSource:
    """Adapter from an admitted :class:`FactorProgram` to :class:`FactorSource`.

    Compilation goes through :class:`mira.factors.evaluator.CompiledProgram`, which runs the static
    checker and refuses inadmissible code; factor errors at run time become counted zero columns
    there (see its ``health``), so a bad value never reaches Φ.
    """

    def __init__(self, program: FactorProgram, card: TaskCard) -> None:
        from mira.factors.evaluator import CompiledProgram

        self.program = program
        self.card = card
        self.compiled = CompiledProgram(program, card)
        meta: dict[str, FactorMeta] = {}
        for f in program.phi_factors:
            lo, hi = range_bounds(f.range_hint)
            meta[f.name] = FactorMeta(lo, hi, f.polarity, f.units)
        self._meta = meta

    @property
    def phi_names(self) -> list[str]:
        return self.compiled.phi_names

    @property
    def aux_names(self) -> list[str]:
        return self.compiled.aux_names

    @property
    def meta(self) -> Mapping[str, FactorMeta]:
        return self._meta

    @property
    def version(self) -> int:
        return self.program.version

    @property
    def shape_names(self) -> list[str]:
        """The program's SHAPE factors: HARS adds γΨ(s′) − Ψ(s) of their sum Ψ to the agent's reward."""
        return self.compiled.shape_names

    def phi(self, obs: np.ndarray) -> np.ndarray:
        return self.compiled.phi(self.card.state_view(obs))

    def shape(self, obs: np.ndarray) -> np.ndarray:
        """Ψ(s) of raw observations ``[B, obs_dim]``: the sum of the SHAPE factors, float64 ``[B]``."""
        return self.compiled.shape(self.card.state_view(obs)).sum(axis=1)

    def aux(self, obs: np.ndarray, act: np.ndarray) -> np.ndarray:
        return self.compiled.aux(self.card.state_view(obs), act)
