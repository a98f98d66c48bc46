"""MIRA: metacognitive, LLM-driven reward design for sparse-reward reinforcement learning.

The package is laid out along the paper's modules and the data that flows between them
(``docs/architecture.md`` has the layers and the import graph)::

    tasks/      task cards (named state features) and the episodic-reward environment wrapper
    factors/    typed reward-factor programs: model, static checker, sandbox, compiler, edit operators
    engineer/   the reward engineer: LSFS and SRR prompts and parsing, backends, the offline rule-based engineer
    llm/        LLM transport: request/reply types, OpenAI-compatible and scripted backends, cache, budget, audit
    shaping/    HARS: factor columns, decomposition head, factor attention, value potential, the reward source
    agents/     SAC and DDPG (PyTorch), sharing networks
    replay      the replay buffer
    rewards/    the reward-source interface and the simple sources (dense oracle, sparse episodic)
    loop/       the one trainer and evaluation
    baselines/  LaRe, RD, IRCR and VIB reward sources
    mcm/        metacognitive monitoring: diagnostics, KDE healthy model, trigger
    srr/        semantic reward reframing: evidence rules, candidate checks, the accept/back-off decision
    outer/      MIRA's outer loop (Algorithm 3) as a trainer hook, and the structural-flaw trigger
    methods/    from a method name to its reward source and hooks
    runio/      run directories: atomic files, CSV logs, checkpoints
    experiments/ sweeps, metrics, reports

The Python interface (README, "Python API"): :func:`train` (``mira train`` as a function),
:func:`load_policy` (a trained policy: ``predict(obs)``), :func:`evaluate` (``mira eval``), and
:class:`Policy`. They are imported on first use, so that ``import mira`` stays instant.
"""

import importlib
from typing import Any

from mira.version import __version__

# The public names, each imported from its module on first use. They are a facade over modules of every
# layer, which nothing inside MIRA imports through the package (scripts/import_graph.py sees no arrow
# here: the modules are named as strings).
_PUBLIC = {"train": "mira.api", "TrainedRun": "mira.api", "evaluate": "mira.api",
           "load_policy": "mira.agents.policy_file", "Policy": "mira.agents.policy_file"}

__all__ = ["Policy", "TrainedRun", "__version__", "evaluate", "load_policy", "train"]


def __getattr__(name: str) -> Any:
    module = _PUBLIC.get(name)
    if module is None:
        raise AttributeError(f"module 'mira' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
