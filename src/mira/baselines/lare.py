"""LaRe — Latent Reward (Qu et al., AAAI 2025, "Latent Reward: LLM-Empowered Credit Assignment in
Episodic Reinforcement Learning").

Definition: an LLM, prompted with the task and its state/action semantics, writes a function that
maps a state–action pair to a vector of interpretable *latent reward* factors; candidate functions
are checked by executing them (self-verification) and one is kept for the whole run. A reward
decoder f_ψ over the factor vector is then trained by return decomposition — RRD's randomized
estimator, regressing T/K · Σ_{t∈I} f_ψ(z_t) on the episodic return R over random K-step subsets I —
and the agent (SAC / TD3 in the paper) learns on the decoded per-step reward f_ψ(z_t).

Ours:

* **The latent function is a MIRA factor program** (DESIGN.md's JSON contract: PHI factors of s, AUX
  factors of (s, a)), obtained once through the same reward-engineer backends, cache, budget and
  audit log as LSFS (:func:`mira.engineer.backends.make_backend`, request purpose ``"lare"``), with the
  LSFS prompt (:func:`mira.engineer.lsfs_prompt.build_lsfs_messages`) plus a LaRe section
  (``prompts/lare_note.txt``) saying the factors feed a return-decomposition decoder. The ``offline``
  engineer answers with its LSFS program (it cannot read prose). The program is **never revised**.
* **Self-verification = MIRA's factor checks**: the reply is parsed strictly
  (:func:`mira.engineer.lsfs_prompt.parse_program_reply`), statically checked, and run in the sandbox
  on real states. A rejected reply is shown back to the LLM with the reasons, up to ``llm.followups``
  times (``llm.followups + 1`` requests, as for LSFS); LaRe instead samples several candidates and keeps
  a passing one — one conversation with feedback costs fewer calls and is deterministic at temperature 0.
* Factors are evaluated in-process by the compiled evaluator (:class:`mira.factors.CompiledProgram`:
  only admitted code, non-finite values zeroed and counted).
* The decoder is an MLP over the z-scored factor values (LaRe's MuJoCo decoder is a small network
  over the latent factors too); loss and reward scaling are those of :mod:`mira.baselines.common`
  (RRD by default, RD's full-episode loss with ``loss="full"``).
* Program origin, in order: ``RUN_DIR/programs/v000.json`` if it exists (a resumed run never asks
  again), ``--program FILE``, then the LLM. The program is saved there before training starts; the
  synthesis attempts are in ``RUN_DIR/lare/synthesis.json`` and every exchange in the LLM audit log.
* The decoder is built against a small protocol (:class:`LatentFactors`: ``phi(obs)``,
  ``aux(obs, act)``), so synthetic factors can stand in for a program in tests.
"""

from __future__ import annotations

import logging
from dataclasses import replace
from importlib import resources
from pathlib import Path
from string import Template
from typing import TYPE_CHECKING, Any, ClassVar, Protocol

import numpy as np
import torch
from torch import nn

from mira.baselines.common import ReturnDecompositionSource, mlp
from mira.baselines.config import LaReConfig
from mira.errors import UsageError

if TYPE_CHECKING:
    from mira.factors.evaluator import CompiledProgram
    from mira.factors.program import FactorProgram
    from mira.llm.base import LLMBackend
    from mira.llm.config import LLMConfig
    from mira.tasks.card import TaskCard

log = logging.getLogger(__name__)

PROGRAM_FILE = Path("programs") / "v000.json"
SYNTHESIS_FILE = Path("lare") / "synthesis.json"


class LatentFactors(Protocol):
    """What the decoder needs from a latent-reward function."""

    @property
    def names(self) -> list[str]: ...

    def phi(self, obs: np.ndarray) -> np.ndarray:
        """State factors of ``obs`` ``[B, obs_dim]``: ``[B, K_phi]``."""
        ...

    def aux(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """State–action factors: ``[B, K_aux]``."""
        ...


class ProgramFactors:
    """A factor program as :class:`LatentFactors`: compiled once, evaluated on observation batches."""

    def __init__(self, program: FactorProgram, card: TaskCard) -> None:
        from mira.factors.evaluator import CompiledProgram

        self.program = program
        self.card = card
        self.compiled: CompiledProgram = CompiledProgram(program, card)

    @property
    def names(self) -> list[str]:
        return self.compiled.phi_names + self.compiled.aux_names

    def phi(self, obs: np.ndarray) -> np.ndarray:
        return self.compiled.phi(self.card.state_view(obs))

    def aux(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        if not self.compiled.aux_names:
            return np.zeros((obs.shape[0], 0))
        return self.compiled.aux(self.card.state_view(obs), action)

    def both(self, obs: np.ndarray, action: np.ndarray) -> np.ndarray:
        """PHI then AUX factors with one state view: ``[B, K]``."""
        view = self.card.state_view(obs)
        parts = [self.compiled.phi(view)]
        if self.compiled.aux_names:
            parts.append(self.compiled.aux(view, action))
        return np.concatenate(parts, axis=1)


class LaReReward(ReturnDecompositionSource):
    """Reward decoder over static latent factors, trained by return decomposition."""

    name = "lare"
    loss_field = "lare_loss"
    log_fields: ClassVar[tuple[str, ...]] = ("lare_loss", "corr_dense")

    def __init__(
        self,
        factors: LatentFactors,
        config: LaReConfig | None = None,
        *,
        origin: str = "",
    ) -> None:
        super().__init__(config or LaReConfig())
        self.factors = factors
        self.origin = origin
        self._dim = len(factors.names)
        if self._dim == 0:
            raise ValueError("lare: the latent-reward function has no factors")

    def input_dim(self) -> int:
        return self._dim

    def raw_inputs(self, obs: torch.Tensor, action: torch.Tensor) -> torch.Tensor:
        o = obs.detach().to("cpu", torch.float64).numpy()
        a = action.detach().to("cpu", torch.float64).numpy()
        both = getattr(self.factors, "both", None)  # one state view for PHI and AUX when offered
        z = both(o, a) if both is not None else np.concatenate((self.factors.phi(o), self.factors.aux(o, a)), 1)
        return torch.as_tensor(z, dtype=torch.float32).to(self.device)

    def build_model(self, in_dim: int) -> nn.Module:
        return mlp(in_dim, tuple(self.config.hidden), 1)

    def predict(self, x: torch.Tensor, *, train: bool) -> tuple[torch.Tensor, torch.Tensor | None]:
        return self.model(x).squeeze(-1), None

    def describe(self) -> dict[str, Any]:
        info = {**super().describe(), "factors": list(self.factors.names), "origin": self.origin}
        program = getattr(self.factors, "program", None)
        if program is not None:
            info["program_version"] = program.version
            info["program_sha256"] = program.content_hash()
        return info


# ------------------------------------------------------------------------------ program synthesis


def _prompt(name: str) -> Template:
    return Template(resources.files("mira.baselines").joinpath("prompts", name).read_text(encoding="utf-8"))


def lare_messages(card: TaskCard, action_dim: int) -> list[dict[str, str]]:
    """The LSFS prompt (same factor language and output format) plus LaRe's latent-reward section."""
    from mira.engineer.lsfs_prompt import build_lsfs_messages

    messages = [dict(m) for m in build_lsfs_messages(card, action_dim)]
    note = _prompt("lare_note.txt").substitute().strip()
    messages[-1]["content"] = messages[-1]["content"].rstrip() + "\n\n" + note
    return messages


def lare_context(card: TaskCard, action_dim: int) -> dict[str, Any]:
    """The structured facts the prompt renders (read only by the offline engineer)."""
    return {
        "task": card.name,
        "description": card.description,
        "features": [{"name": f.name, "units": f.units, "doc": f.doc} for f in card.features],
        "action_dim": int(action_dim),
    }


def check_lare_program(program: FactorProgram, card: TaskCard, *, sandbox: bool, seed: int = 0) -> list[str]:
    """Reasons to reject ``program`` (empty: admissible): the static checker, then the sandbox."""
    from mira.factors.checker import check_program

    report = check_program(program, card.feature_names)
    if not report.ok:
        return [str(v) for v in report.errors]
    if sandbox:
        from mira.factors.sandbox import sandbox_check

        result = sandbox_check(program, card, seed=seed)
        if not result.ok:
            return result.lines() or ["the sandbox check failed"]
    return []


def synthesize_lare_program(
    card: TaskCard, action_dim: int, backend: LLMBackend, *, max_requests: int, seed: int = 0
) -> tuple[FactorProgram, list[dict[str, Any]]]:
    """Ask ``backend`` for the latent-reward program; returns it and a record of every attempt.

    ``max_requests`` is a run's ``llm.followups + 1`` (the offline engineer's first answer is admissible;
    it reads no feedback). Raises :class:`UsageError` naming the last reasons when no admissible program
    came back within them.
    """
    from mira.engineer.backends import find_layer
    from mira.engineer.lsfs_prompt import parse_program_reply
    from mira.factors.program import ProgramParseError
    from mira.llm.audit import AuditedBackend
    from mira.llm.base import LLMRequest

    if max_requests <= 0:
        raise UsageError(f"lare: llm.followups must be >= 0, not {max_requests - 1}")
    messages = lare_messages(card, action_dim)
    context = lare_context(card, action_dim)
    audit = find_layer(backend, AuditedBackend)
    attempts: list[dict[str, Any]] = []
    reasons: list[str] = []
    for attempt in range(max_requests):
        request = LLMRequest(messages=list(messages), purpose="lare", temperature=0.0,
                             context={**context, "attempt": attempt, "previous_rejection": reasons})
        reply = backend.complete(request)
        try:
            program = parse_program_reply(reply.content, card)
            reasons = check_lare_program(program, card, sandbox=True, seed=seed)
        except ProgramParseError as exc:
            reasons = [str(exc)]
        ok = not reasons
        record = {"attempt": attempt, "ok": ok, "reasons": list(reasons), "backend": reply.backend,
                  "model": reply.model, "cached": reply.cached}
        attempts.append(record)
        if audit is not None:
            audit.record_parse_result(reply, {"ok": ok, "reasons": list(reasons), "use": "lare"})
        if ok:
            return program, attempts
        log.warning("lare: attempt %d rejected: %s", attempt + 1, "; ".join(reasons))
        messages = [*messages, {"role": "assistant", "content": reply.content},
                    {"role": "user", "content": _prompt("lare_retry.txt").substitute(
                        reasons="\n".join(f"- {r}" for r in reasons)).strip()}]
    raise UsageError(f"lare: no admissible latent-reward program after {max_requests} request(s): "
                     + "; ".join(reasons))


def make_lare_backend(llm: LLMConfig, run_dir: Path) -> LLMBackend:
    from mira.engineer.lsfs import backend_from_config

    return backend_from_config(llm, Path(run_dir) / "llm" / "cache", Path(run_dir))


def lare_program(
    card: TaskCard,
    run_dir: Path,
    llm: LLMConfig,
    *,
    program_file: str | None = None,
    seed: int = 0,
    backend: LLMBackend | None = None,
) -> tuple[FactorProgram, str]:
    """The run's static latent-reward program and where it came from (see the module docstring)."""
    from mira.factors.program import load_program
    from mira.runio.atomic import atomic_write_json

    saved = Path(run_dir) / PROGRAM_FILE
    if saved.is_file():
        program = load_program(saved)
        reasons = check_lare_program(program, card, sandbox=False)
        if reasons:
            raise UsageError(f"{saved}: the saved LaRe program is not admissible: " + "; ".join(reasons))
        return program, f"saved program {saved}"
    if program_file:
        program = load_program(program_file)
        if program.task != card.name:
            raise UsageError(f"--program {program_file}: it is a program for task {program.task!r}, not {card.name!r}")
        if program.version != 0:
            program = replace(program, version=0, parent_version=None, edits=(), diff="")
        reasons = check_lare_program(program, card, sandbox=True, seed=seed)
        if reasons:
            raise UsageError(f"--program {program_file}: not admissible: " + "; ".join(reasons))
        origin = f"program file {program_file}"
        attempts: list[dict[str, Any]] = []
    else:
        engine = backend if backend is not None else make_lare_backend(llm, run_dir)
        from mira.tasks.envs import action_dim

        program, attempts = synthesize_lare_program(card, action_dim(card), engine, max_requests=llm.followups + 1,
                                                    seed=seed)
        origin = f"reward engineer {llm.backend}"
    atomic_write_json(saved, program.to_json())
    atomic_write_json(Path(run_dir) / SYNTHESIS_FILE, {"origin": origin, "attempts": attempts,
                                                      "factors": program.names})
    return program, origin
