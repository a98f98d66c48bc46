"""Fast, in-process evaluation of *admitted* factor programs on batches of states.

Training evaluates the factors on every sampled batch, so they cannot each cross a process
boundary; they run here, in the trainer's process, as plain Python functions over NumPy arrays.

Why that does not reopen the hole the sandbox closes:

* Only code that passes the AST whitelist is compiled: :class:`CompiledProgram` calls
  :func:`mira.factors.compiler.compile_factor`, which runs the checker itself and refuses any error,
  so there is no path from an unchecked string to ``exec``.
* The whitelist leaves no route out of the function. There are no imports, no names beginning with
  ``_`` (so no ``__class__``/``__globals__``/``__subclasses__`` walks), no attribute access except
  ``s.<declared feature>``, ``s.obs`` and ``np.<whitelisted>``, no builtins except ``abs``, ``min``,
  ``max`` and ``float`` (the globals dict has ``__builtins__ = {}``), no strings, and no function
  that reads or writes files, sockets or process state. ``np`` is a read-only proxy exposing only
  the whitelisted functions; ``s`` is a read-only view whose arrays are read-only.
* Cost is bounded whatever the data: loops only over small constant ranges, a static operation
  bound, functions that allocate no more than their inputs, and no Python big integers (literals
  become NumPy float64). So a branch the sandbox did not take cannot hang or exhaust memory.
* Outputs are distrusted too: each is cast to float64 of shape ``[B]`` (a wrong shape, a wrong dtype
  or an exception yields a column of zeros and is counted), and NaN/Inf are replaced by 0 and
  counted in :attr:`CompiledProgram.health`, so a bad value never reaches Φ or the replay buffer.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from mira.errors import MiraError
from mira.factors.checker import check_program, feature_names_of
from mira.factors.compiler import FactorFunction, InadmissibleCodeError, compile_factor
from mira.factors.program import Factor, FactorProgram

if TYPE_CHECKING:
    from mira.tasks.card import StateView, TaskCard


class FactorRuntimeError(MiraError):
    """A factor failed at run time and the program was compiled with ``strict=True``."""


@dataclass
class FactorHealth:
    """Running counts of what went wrong in one factor (:attr:`CompiledProgram.health`, one per factor)."""

    calls: int = 0
    errors: int = 0
    bad_shape: int = 0
    nonfinite_values: int = 0
    last_error: str = ""

    def to_dict(self) -> dict[str, Any]:
        return dict(vars(self))


class CompiledProgram:
    """An admitted program compiled once, evaluated many times on :class:`StateView` batches.

    ``phi(view)`` gives ``[B, K_phi]`` (the inputs of Φ), ``aux(view, actions)`` ``[B, K_aux]``,
    ``shape(view)`` ``[B, K_shape]``, all float64 and finite. With ``strict=True`` a factor error raises
    :class:`FactorRuntimeError` instead of producing a zero column (useful in tests and checks, not in training).
    """

    def __init__(
        self, program: FactorProgram, card: TaskCard | Sequence[str], *, strict: bool = False
    ) -> None:
        features = feature_names_of(card) or []
        report = check_program(program, features)
        if not report.ok:
            raise InadmissibleCodeError(report.errors)
        self.program = program
        self.strict = strict
        self._phi: list[tuple[Factor, FactorFunction]] = [
            (f, compile_factor(f.name, f.type, f.code, features)) for f in program.phi_factors
        ]
        self._aux: list[tuple[Factor, FactorFunction]] = [
            (f, compile_factor(f.name, f.type, f.code, features)) for f in program.aux_factors
        ]
        self._shape: list[tuple[Factor, FactorFunction]] = [
            (f, compile_factor(f.name, f.type, f.code, features)) for f in program.shape_factors
        ]
        self.health: dict[str, FactorHealth] = {f.name: FactorHealth() for f in program.factors}

    @property
    def phi_names(self) -> list[str]:
        return [f.name for f, _ in self._phi]

    @property
    def aux_names(self) -> list[str]:
        return [f.name for f, _ in self._aux]

    @property
    def shape_names(self) -> list[str]:
        return [f.name for f, _ in self._shape]

    @property
    def version(self) -> int:
        return self.program.version

    def phi(self, view: StateView) -> np.ndarray:
        """Every PHI factor on a batch of states: float64 ``[B, K_phi]``."""
        return self._of_states(self._phi, view)

    def _of_states(self, compiled: list[tuple[Factor, FactorFunction]], view: StateView) -> np.ndarray:
        """State-only factors (PHI or SHAPE) on a batch of states: float64 ``[B, K]``, finite."""
        batch = int(view.obs.shape[0])
        out = np.empty((batch, len(compiled)), dtype=np.float64)
        with np.errstate(all="ignore"):
            for j, (factor, fn) in enumerate(compiled):
                out[:, j] = self._run(factor, fn, batch, (view,))
        return self._finite(out, compiled)

    def aux(self, view: StateView, actions: np.ndarray) -> np.ndarray:
        """Every AUX factor on a batch of states and actions ``[B, act_dim]``: float64 ``[B, K_aux]``."""
        batch = int(view.obs.shape[0])
        acts = np.asarray(actions, dtype=np.float64)
        acts = (acts[None, :] if acts.ndim == 1 else acts).view()  # a read-only view: no copy, no writes
        acts.setflags(write=False)
        if acts.ndim != 2 or acts.shape[0] != batch:
            raise ValueError(f"actions have shape {acts.shape}; expected [{batch}, act_dim]")
        out = np.empty((batch, len(self._aux)), dtype=np.float64)
        with np.errstate(all="ignore"):
            for j, (factor, fn) in enumerate(self._aux):
                out[:, j] = self._run(factor, fn, batch, (view, acts))
        return self._finite(out, self._aux)

    def shape(self, view: StateView) -> np.ndarray:
        """Every SHAPE factor on a batch of states: float64 ``[B, K_shape]`` (their sum is Ψ)."""
        return self._of_states(self._shape, view)

    def evaluate(self, view: StateView, actions: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Each factor's values by name (AUX factors only when ``actions`` are given)."""
        values = dict(zip(self.phi_names, self.phi(view).T, strict=True))
        if self._shape:
            values.update(zip(self.shape_names, self.shape(view).T, strict=True))
        if actions is not None and self._aux:
            values.update(zip(self.aux_names, self.aux(view, actions).T, strict=True))
        return values

    def _run(self, factor: Factor, fn: FactorFunction, batch: int, args: tuple[Any, ...]) -> np.ndarray:
        health = self.health[factor.name]
        health.calls += 1
        try:
            raw = fn(*args)
            values = np.asarray(raw)
            if values.dtype.kind not in "fiub":
                raise TypeError(f"returned dtype {values.dtype}")
            values = values.astype(np.float64, copy=False)
        except Exception as exc:  # untrusted code: any failure becomes a counted zero column
            health.errors += 1
            health.last_error = f"{type(exc).__name__}: {exc}"[:300]
            if self.strict:
                raise FactorRuntimeError(f"factor {factor.name!r}: {health.last_error}") from exc
            return np.zeros(batch)
        if values.shape != (batch,):
            health.bad_shape += 1
            health.last_error = f"returned shape {values.shape}, expected ({batch},)"
            if self.strict:
                raise FactorRuntimeError(f"factor {factor.name!r}: {health.last_error}")
            return np.zeros(batch)
        return values

    def _finite(self, out: np.ndarray, compiled: list[tuple[Factor, FactorFunction]]) -> np.ndarray:
        """Replace NaN/Inf by 0, counting them per factor (one check for the whole matrix)."""
        finite = np.isfinite(out)
        if finite.all():
            return out
        for j, (factor, _) in enumerate(compiled):
            bad = int(out.shape[0] - np.count_nonzero(finite[:, j]))
            if bad:
                self.health[factor.name].nonfinite_values += bad
                if self.strict:
                    raise FactorRuntimeError(f"factor {factor.name!r}: {bad} non-finite value(s)")
        out[~finite] = 0.0
        return out
