"""Reward-factor programs as first-class, safe objects (sections 4.2.1, 4.4.1 and 4.4.4 of the paper).

A factor is a small typed function of the state (PHI, may feed the potential Φ) or of state and
action (AUX, policy-side only), written by an LLM and treated as untrusted code:

* :mod:`.program`   the program model and its JSON contract (load/save, hash, diff);
* :mod:`.checker`   static integrity by an AST whitelist, violations with rule ids and lines;
* :mod:`.sandbox`   realizability on real states in a separate, resource-limited process;
* :mod:`.evaluator` fast in-process evaluation of admitted programs during training;
* :mod:`.edits`     the admissible edit operators (Scale, Sat, Gate, Refactor, Add, Prune);
* :mod:`.examples`  the paper's section 5.3 programs for HalfCheetah and HumanoidStandup.
"""

from mira.factors.checker import StaticReport, check_code, check_factor, check_program, parse_range_hint
from mira.factors.compiler import InadmissibleCodeError, compile_factor
from mira.factors.edits import (
    Add,
    EditError,
    Gate,
    Prune,
    Refactor,
    Sat,
    Scale,
    apply_edit,
    apply_edits,
    edit_from_json,
)
from mira.factors.evaluator import CompiledProgram, FactorHealth, FactorRuntimeError
from mira.factors.examples import example_program, example_programs
from mira.factors.program import (
    Factor,
    FactorProgram,
    ProgramParseError,
    code_diff,
    load_program,
    save_program,
)
from mira.factors.sandbox import (
    FactorVerdict,
    SandboxLimits,
    SandboxReport,
    SandboxThresholds,
    collect_states,
    sandbox_check,
)
from mira.factors.violations import RULES, Violation

__all__ = [
    "RULES",
    "Add",
    "CompiledProgram",
    "EditError",
    "Factor",
    "FactorHealth",
    "FactorProgram",
    "FactorRuntimeError",
    "FactorVerdict",
    "Gate",
    "InadmissibleCodeError",
    "ProgramParseError",
    "Prune",
    "Refactor",
    "SandboxLimits",
    "SandboxReport",
    "SandboxThresholds",
    "Sat",
    "Scale",
    "StaticReport",
    "Violation",
    "apply_edit",
    "apply_edits",
    "check_code",
    "check_factor",
    "check_program",
    "code_diff",
    "collect_states",
    "compile_factor",
    "edit_from_json",
    "example_program",
    "example_programs",
    "load_program",
    "parse_range_hint",
    "sandbox_check",
    "save_program",
]
