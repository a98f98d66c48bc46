"""The ``mira train`` command line: its arguments and the :class:`TrainConfig` they make.

Defaults and help texts come from the configuration dataclasses (their field docstrings), so a flag
cannot drift from the field it sets. ``mira sweep`` validates its pass-through train arguments with
the same definitions.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import itertools
import json
import textwrap
from functools import cache
from typing import Any

from mira.agents import ALGOS
from mira.agents.base import AgentConfig
from mira.cli_types import hidden_widths, nonneg_int, positive_int
from mira.config import PRESETS, TrainConfig, apply_override
from mira.llm.config import LLMConfig
from mira.methods import METHODS
from mira.tasks.card import builtin_task_names


@cache
def field_docs(cls: type) -> dict[str, str]:
    """Each field's docstring (the string literal written after it), whitespace collapsed."""
    tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    body = tree.body[0].body if tree.body and isinstance(tree.body[0], ast.ClassDef) else []
    docs: dict[str, str] = {}
    for node, after in itertools.pairwise(body):
        if (isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and isinstance(after, ast.Expr)
                and isinstance(after.value, ast.Constant) and isinstance(after.value.value, str)):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def _help(cls: type, name: str, extra: str = "") -> str:
    """The field's docstring (``extra`` appended) and its default, as a flag's help."""
    doc = field_docs(cls).get(name, "").replace("%", "%%")
    return f"{doc}{extra} (default: {getattr(cls(), name)})"


def add_llm_flags(p: argparse.ArgumentParser) -> None:
    """Who writes and edits programs (see :class:`~mira.llm.config.LLMConfig`)."""
    p.add_argument("--llm", default=LLMConfig.backend, metavar="BACKEND", help=_help(LLMConfig, "backend"))
    p.add_argument("--base-url", default=None, help=_help(LLMConfig, "base_url"))
    p.add_argument("--api-key-env", default=LLMConfig.api_key_env, help=_help(LLMConfig, "api_key_env"))
    p.add_argument("--llm-cache", default=None, metavar="DIR", help=_help(LLMConfig, "cache_dir"))
    p.add_argument("--llm-offline-only", action="store_true", help=_help(LLMConfig, "offline_only"))


def add_train_arguments(t: argparse.ArgumentParser) -> None:
    """Every ``mira train`` flag."""
    c = TrainConfig
    builtin = ", ".join(builtin_task_names())
    t.add_argument("--task", default=c.task, help=_help(c, "task", extra=f" Built in: {builtin}."))
    t.add_argument("--method", default=None, choices=sorted(METHODS),
                   help=_help(c, "method", extra=" With --fork: the parent's unless given."))
    t.add_argument("--algo", default=c.algo, choices=ALGOS, help=_help(c, "algo"))
    t.add_argument("--steps", type=positive_int, default=None,
                   help=_help(c, "steps", extra=" With --resume, a larger budget extends the run."))
    t.add_argument("--seed", type=nonneg_int, default=None,
                   help=_help(c, "seed", extra=" With --fork: the fork's own (default: the parent's)."))
    t.add_argument("--out", default=None, help="run directory (required unless --resume)")
    t.add_argument("--resume", default=None, metavar="DIR", help="continue the run in DIR from its last checkpoint")
    t.add_argument("--overwrite", action="store_true", help="replace an existing non-empty --out directory")
    t.add_argument("--fork", default=None, metavar="RUN_DIR",
                   help="start --out from a checkpoint of RUN_DIR under a seed of its own (--seed): the parent's "
                        "configuration, with --steps, --method (among mira, mira-no-mcm, mira-no-srr), the LLM "
                        "flags and --set mira.*/llm.*/hars.* changed as given; for paired experiments")
    t.add_argument("--fork-step", type=positive_int, default=None, metavar="STEP",
                   help="the parent's checkpoint to fork from (default: its newest)")
    t.add_argument("--fork-program", default=None, metavar="FILE",
                   help="with --fork (a mira method): install this factor program at the fork, as an accepted edit "
                        "is installed, after the checker admits it: the A/B test of a reward edit from one state")
    t.add_argument("--learning-starts", type=nonneg_int, default=c.learning_starts, help=_help(c, "learning_starts"))
    t.add_argument("--buffer-size", type=positive_int, default=c.buffer_size, help=_help(c, "buffer_size"))
    t.add_argument("--batch-size", type=positive_int, default=AgentConfig.batch_size,
                   help=_help(AgentConfig, "batch_size"))
    t.add_argument("--lr", type=float, default=None,
                   help=_help(AgentConfig, "lr", extra=" Sets HARS's learning rate too."))
    t.add_argument("--preset", choices=sorted(PRESETS), default=None,
                   help="a named set of defaults applied before --lr and --set: 'paper' = Table 1 of the "
                        "paper (lr 1e-4 for the agent and HARS, ΔT 5,000, the anomaly trigger alone); "
                        "'paper-letter' = that and section 4.2's Φ aligned to the episodic reward, κ = 1")
    t.add_argument("--hidden", type=hidden_widths, default=AgentConfig().hidden,
                   help=_help(AgentConfig, "hidden", extra=" Comma-separated, e.g. 256,256."))
    t.add_argument("--eval-every", type=positive_int, default=c.eval_every, help=_help(c, "eval_every"))
    t.add_argument("--eval-episodes", type=positive_int, default=c.eval_episodes, help=_help(c, "eval_episodes"))
    t.add_argument("--checkpoint-every", type=positive_int, default=c.checkpoint_every,
                   help=_help(c, "checkpoint_every"))
    t.add_argument("--log-every", type=positive_int, default=c.log_every, help=_help(c, "log_every"))
    t.add_argument("--max-episode-steps", type=positive_int, default=None, help=_help(c, "max_episode_steps"))
    t.add_argument("--device", default=c.device, choices=("auto", "cpu", "cuda"), help=_help(c, "device"))
    t.add_argument("--threads", type=positive_int, default=c.threads, help=_help(c, "threads"))
    t.add_argument("--program", default=None, help=_help(c, "program"))
    t.add_argument("--set", dest="overrides", action="append", default=[], metavar="KEY=VALUE",
                   help="override any config field, e.g. --set mira.mcm.delta_t=1000 --set hars.shaping_weight=1")
    t.add_argument("--quiet", action="store_true", help="log lines instead of a progress bar")
    t.add_argument("--show-config", action="store_true",
                   help="print every configuration key (what --set takes) with the value this command line gives "
                        "it and its docstring, then exit without training or writing anything")
    add_llm_flags(t)


def config_from_args(args: argparse.Namespace) -> TrainConfig:
    """The run's configuration: the dataclass defaults, then ``--preset``, the flags, ``--lr`` and ``--set``."""
    cfg = TrainConfig(
        task=args.task, method=TrainConfig.method if args.method is None else args.method, algo=args.algo,
        steps=TrainConfig.steps if args.steps is None else args.steps,
        seed=TrainConfig.seed if args.seed is None else args.seed,
        learning_starts=args.learning_starts, buffer_size=args.buffer_size, eval_every=args.eval_every,
        eval_episodes=args.eval_episodes, checkpoint_every=args.checkpoint_every, log_every=args.log_every,
        max_episode_steps=args.max_episode_steps, device=args.device, threads=args.threads, program=args.program,
    )
    for assignment in PRESETS.get(args.preset or "", ()):
        apply_override(cfg, assignment)
    cfg.agent.batch_size, cfg.agent.hidden = args.batch_size, args.hidden
    if args.lr is not None:
        cfg.agent.lr = cfg.hars.lr = args.lr
    cfg.llm.backend, cfg.llm.base_url, cfg.llm.api_key_env = args.llm, args.base_url, args.api_key_env
    cfg.llm.cache_dir, cfg.llm.offline_only = args.llm_cache, args.llm_offline_only
    for assignment in args.overrides:
        apply_override(cfg, assignment)
    return cfg


def train_parser(prog: str = "mira train") -> argparse.ArgumentParser:
    """A stand-alone parser of ``mira train``'s flags (what ``mira sweep`` checks train args with)."""
    from mira.cli_types import Parser

    parser = Parser(prog=prog)
    add_train_arguments(parser)
    return parser


def describe_config(cfg: TrainConfig) -> str:
    """Every key ``--set`` accepts, as ``key = value`` (the value in ``--set``'s JSON syntax) over its docstring."""
    lines: list[str] = []

    def walk(section: Any, prefix: str) -> None:
        section_type: type = type(section)
        docs = field_docs(section_type)
        for f in dataclasses.fields(section):
            value = getattr(section, f.name)
            if dataclasses.is_dataclass(value):
                walk(value, f"{prefix}{f.name}.")
                continue
            lines.append(f"{prefix}{f.name} = {json.dumps(value)}")
            if doc := docs.get(f.name):
                lines.extend(textwrap.wrap(doc, 100, initial_indent="    # ", subsequent_indent="    # "))

    walk(cfg, "")
    return "\n".join(lines)
