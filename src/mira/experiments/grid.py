"""Sweep grids: tasks × methods × algos × seeds at a step budget, with extra ``mira train`` flags.

A grid comes from command-line flags, a named preset, or a sweep file (TOML or YAML) that can be
versioned next to the code. Later sources override earlier ones key by key: preset, then file, then
flags (``train_args`` are appended instead, and the last occurrence of a flag wins). Every value is
checked before anything runs; bad input raises :class:`~mira.errors.UsageError` with a one-line
message that names the problem.

Sweep file keys (all optional except that the merged grid must name tasks, methods, algos, seeds and
steps)::

    preset      = "paper-small"                 # start from a preset, then override
    tasks       = ["halfcheetah", "humanoidstandup"]   # built-in names or task-card paths
    programs    = ["task", "flawed/no_progress.json"]  # initial programs ("task": the task's own)
    methods     = ["dense", "sparse", "mira"]   # "all" = every method registered in mira.methods
    algos       = ["sac"]
    seeds       = 3                             # an integer K means seeds 0..K-1; or a list [0, 1, 2]
    steps       = 30000
    train_args  = "--eval-episodes 3"           # extra `mira train` flags (string or list)
    workers     = 2                             # local pool size
    backend     = "pool"                        # or "ray"
    address     = "auto"                        # Ray cluster address (backend "ray")
    cpus_per_run = 1                            # Ray: CPUs reserved per run
    retries     = 1                             # re-attempts of a failed run within one sweep

    [train]                                     # `mira train` flags as a table (before train_args)
    eval-every = 1000
    hidden = [256, 256]                         # lists are joined with commas
    quiet = true                                # true = bare flag, false = left out
"""

from __future__ import annotations

import contextlib
import io
import shlex
import tomllib
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mira.errors import UsageError

# Flags the grid owns: a run's identity and its directory. They may not be passed through.
GRID_FLAGS = ("--task", "--program", "--method", "--algo", "--seed", "--steps", "--out", "--resume", "--overwrite",
              "--fork", "--fork-step")

TASK_PROGRAM = "task"
"""In a list of initial programs, the task's own program (``mira train`` without ``--program``)."""

# The paper's method order in Tables 2/3, ablations next to MIRA; unknown methods follow, sorted.
METHOD_ORDER = ("dense", "mira", "mira-no-mcm", "mira-no-srr", "lare", "rd", "ircr", "vib", "sparse")

SETTING_KEYS = ("workers", "backend", "address", "cpus_per_run", "retries")
FILE_KEYS = ("preset", "tasks", "programs", "methods", "algos", "seeds", "steps", "train_args", "train", *SETTING_KEYS)


def available_methods() -> list[str]:
    """Every method registered in :data:`mira.methods.METHODS` now, in the paper's table order."""
    from mira.methods import METHODS

    return order_methods(METHODS)


def order_methods(methods: Iterable[str]) -> list[str]:
    names = list(dict.fromkeys(methods))
    known = [m for m in METHOD_ORDER if m in names]
    return known + sorted(m for m in names if m not in METHOD_ORDER)


def task_label(task: str) -> str:
    """Directory-safe name of a task: the built-in name, or a task card file's stem."""
    path = Path(task)
    if path.suffix.lower() in (".toml", ".yaml", ".yml"):
        return path.stem
    return task


def program_label(program: str) -> str:
    """Directory name of an initial program: its file's stem; "" for the task's own program."""
    return Path(program).stem if program else ""


@dataclass(frozen=True)
class RunSpec:
    """One run of a sweep: a normal ``mira train`` run directory under the sweep's output."""

    task: str
    method: str
    algo: str
    seed: int
    steps: int
    train_args: tuple[str, ...] = ()
    program: str = ""
    """The initial program file (``mira train --program``); "" for the task's own program."""

    def _parts(self) -> list[str]:
        label = program_label(self.program)
        return [task_label(self.task), *([label] if label else []), self.algo, self.method, f"seed{self.seed}"]

    @property
    def run_id(self) -> str:
        return "/".join(self._parts())

    def run_dir(self, out: str | Path) -> Path:
        """``OUT/<task>/<algo>/<method>/seed<k>``, with the program's stem after the task when it has one."""
        return Path(out).joinpath(*self._parts())

    def to_dict(self) -> dict[str, Any]:
        return {"task": self.task, "method": self.method, "algo": self.algo, "seed": self.seed,
                "steps": self.steps, "train_args": list(self.train_args), "program": self.program}

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> RunSpec:
        return cls(str(data["task"]), str(data["method"]), str(data["algo"]), int(data["seed"]),
                   int(data["steps"]), tuple(str(a) for a in data.get("train_args", ())),
                   str(data.get("program") or ""))


@dataclass
class SweepGrid:
    """tasks × methods × algos × seeds, each trained for ``steps`` with ``train_args``."""

    tasks: list[str]
    methods: list[str]
    algos: list[str]
    seeds: list[int]
    steps: int
    train_args: list[str] = field(default_factory=list)
    preset: str | None = None
    programs: list[str] = field(default_factory=lambda: [""])
    """Initial program files every run of a task starts from, one run each; "" is the task's own."""

    def runs(self) -> list[RunSpec]:
        """Every run, seed-major so that a partial sweep already covers every method of early seeds;
        within a seed the Dense oracle comes first (sample efficiency is measured against it)."""
        methods = order_methods(self.methods)
        return [RunSpec(t, m, a, s, self.steps, tuple(self.train_args), p)
                for s in self.seeds for t in self.tasks for p in self.programs for a in self.algos
                for m in methods]

    def to_dict(self) -> dict[str, Any]:
        out = {"tasks": list(self.tasks), "methods": list(self.methods), "algos": list(self.algos),
               "seeds": list(self.seeds), "steps": self.steps, "train_args": list(self.train_args),
               "preset": self.preset}
        return out if self.programs == [""] else {**out, "programs": list(self.programs)}

    def validate(self) -> SweepGrid:
        """Check every axis and the pass-through flags; return self."""
        for name in ("tasks", "methods", "algos", "seeds"):
            if not getattr(self, name):
                raise UsageError(f"no {name} given (--{name} or '{name}' in the sweep file)")
        for m in self.methods:
            check_method(m)
        for a in self.algos:
            check_algo(a)
        for t in self.tasks:
            check_task(t)
        labels = [task_label(t) for t in self.tasks]
        if len(set(labels)) != len(labels):
            raise UsageError(f"two tasks share a directory name ({', '.join(labels)})")
        check_programs(self.programs)
        if any(s < 0 for s in self.seeds) or len(set(self.seeds)) != len(self.seeds):
            raise UsageError(f"seeds must be distinct non-negative integers, got {self.seeds}")
        if self.steps <= 0:
            raise UsageError(f"steps must be a positive integer, got {self.steps}")
        check_train_args(self.train_args)
        return self


def check_method(method: str) -> None:
    methods = available_methods()
    if method not in methods:
        raise UsageError(f"unknown method {method!r} (available: {', '.join(methods)})")


def check_algo(algo: str) -> None:
    from mira.agents import ALGOS

    if algo not in ALGOS:
        raise UsageError(f"unknown algo {algo!r} (available: {', '.join(ALGOS)})")


def check_task(task: str) -> None:
    from mira.tasks.card import builtin_task_names

    if task in builtin_task_names():
        return
    path = Path(task)
    if path.suffix.lower() in (".toml", ".yaml", ".yml"):
        if not path.is_file():
            raise UsageError(f"task card {task} does not exist")
        return
    raise UsageError(f"unknown task {task!r} (built-in: {', '.join(builtin_task_names())}, "
                     "or a .toml/.yaml task card)")


def check_programs(programs: Sequence[str]) -> None:
    """Each initial program is "" (the task's own) or an existing file; their directory names differ
    from one another and from the algos' level below the task."""
    if not programs:
        raise UsageError("no programs given (--programs task,FILE.json or 'programs' in the sweep file)")
    for program in programs:
        if program and not Path(program).is_file():
            raise UsageError(f"initial program {program} does not exist")
    labels = [program_label(p) for p in programs]
    if len(set(labels)) != len(labels):
        names = ", ".join(label or TASK_PROGRAM for label in labels)
        raise UsageError(f"two initial programs share a directory name ({names})")
    from mira.agents import ALGOS

    clash = sorted(set(labels) & set(ALGOS))
    if clash:
        raise UsageError(f"an initial program may not be named like an algo ({clash[0]}.json): rename the file")


def parse_programs(value: Any, where: str, base: Path | None = None) -> list[str]:
    """Initial programs from a comma-separated string or a list: ``task`` is the task's own program;
    a file becomes an absolute path (relative ones are read from ``base``, then the working directory),
    so that a run started from another directory (a Ray worker's) finds it."""
    programs = []
    for name in parse_names(value, where):
        if name == TASK_PROGRAM:
            programs.append("")
            continue
        path = Path(name)
        if base is not None and not path.is_absolute() and (base / path).exists():
            path = base / path
        programs.append(str(path.resolve()))
    return programs


def check_train_args(train_args: Sequence[str]) -> None:
    """Reject grid-owned flags and anything ``mira train`` would not accept."""
    for arg in train_args:
        flag = arg.split("=", 1)[0]
        if flag in GRID_FLAGS:
            raise UsageError(f"{flag} is set by the sweep grid and cannot be passed in train args")
        if flag == "--show-config":
            raise UsageError("--show-config prints a configuration and trains nothing: use it with mira train")
    from mira.train_cli import train_parser

    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            train_parser().parse_args(["--out", "_", *train_args])
    except SystemExit:
        lines = [ln for ln in err.getvalue().strip().splitlines() if ln.strip()]
        detail = lines[-1].split("error:", 1)[-1].strip() if lines else "not accepted by mira train"
        raise UsageError(f"bad train args {shlex.join(train_args)!r}: {detail}") from None


# ------------------------------------------------------------------------------------------ presets
# paper-small: a grid a 2-core machine finishes in a few hours (PRESET_NOTES says what it holds).
PAPER_SMALL_STEPS = 30_000
PAPER_SMALL_TRAIN = ["--learning-starts", "5000", "--eval-every", "1500", "--eval-episodes", "3",
                     "--checkpoint-every", "10000", "--log-every", "1000", "--threads", "1"]

PRESET_NOTES = {
    "paper-small": (
        "every registered method × SAC × {halfcheetah, humanoidstandup} × 3 seeds × 30k steps, 2 workers; "
        "Table 1 networks (256×256) and lr 1e-4; learning starts at 5k; evaluation every 1.5k steps on 3 "
        "episodes (20 evaluations; the final-10% window holds the evaluations at 28.5k and 30k = 6 "
        "episodes). Six runs per registered method: for 9 methods, 54 runs × 30k = 1.62M env steps. "
        "A small version of the paper's grid, not its budget: `--dry-run --probe` times it on this machine."
    ),
    "paper": (
        "every registered method × {SAC, DDPG} × {halfcheetah, humanoidstandup, humanoid} × 5 seeds × 1M "
        "steps, every run with `mira train --preset paper` (Table 1: lr 1e-4 for the agent and HARS, "
        "ΔT 5,000, the monitor's anomaly trigger alone; with the defaults γ 0.99, 256×256 MLPs, batch 256, "
        "learning starts 10k, evaluation every 5k steps on 10 episodes). 9 × 2 × 3 × 5 = 270 runs × 1M = "
        "270M env steps: a cluster job (`--backend ray --address auto`); the paper reports 20-40 h per "
        "run on a GPU workstation."
    ),
}


def preset_grid(name: str) -> SweepGrid:
    """A named preset; methods are read from :data:`mira.methods.METHODS` at call time."""
    methods = available_methods()
    if name == "paper-small":
        return SweepGrid(["halfcheetah", "humanoidstandup"], methods, ["sac"], [0, 1, 2], PAPER_SMALL_STEPS,
                         list(PAPER_SMALL_TRAIN), preset=name)
    if name == "paper":
        return SweepGrid(["halfcheetah", "humanoidstandup", "humanoid"], methods, ["sac", "ddpg"],
                         [0, 1, 2, 3, 4], 1_000_000, ["--preset", "paper"], preset=name)
    raise UsageError(f"unknown preset {name!r} (available: {', '.join(PRESET_NOTES)})")


PRESET_SETTINGS: dict[str, dict[str, Any]] = {"paper-small": {"workers": 2}, "paper": {}}


# ------------------------------------------------------------------------------------ value parsing
def parse_seeds(value: Any, where: str = "--seeds") -> list[int]:
    """``3`` → [0, 1, 2]; ``"0,2,5"`` or ``[0, 2, 5]`` → those; ``"0-4"`` → 0..4 inclusive; ``"0"`` (a
    count of none) → [0], seed 0."""
    if isinstance(value, bool):
        raise UsageError(f"{where}: expected a seed count or a list of seeds, got {value!r}")
    if isinstance(value, int):
        if value <= 0:
            raise UsageError(f"{where}: a seed count must be positive, got {value}")
        return list(range(value))
    if isinstance(value, list):
        out: list[int] = []
        for v in value:
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise UsageError(f"{where}: seeds must be non-negative integers, got {v!r}")
            out.append(v)
        return out
    if isinstance(value, str):
        text = value.strip()
        try:
            if "," in text:
                return [int(p) for p in text.split(",") if p.strip()]
            if "-" in text:
                lo, hi = (int(p) for p in text.split("-", 1))
                if hi < lo:
                    raise ValueError
                return list(range(lo, hi + 1))
            if int(text) == 0:  # no count of runs is 0: "--seeds 0" asks for seed 0
                return [0]
            return parse_seeds(int(text), where)
        except ValueError:
            raise UsageError(f"{where}: expected a count (5), a list (0,1,2) or a range (0-4), "
                             f"got {value!r}") from None
    raise UsageError(f"{where}: expected a seed count or a list of seeds, got {type(value).__name__}")


def parse_names(value: Any, where: str) -> list[str]:
    """A list of names from a comma-separated string or a list of strings; ``all`` for methods."""
    if isinstance(value, str):
        items = [p.strip() for p in value.split(",") if p.strip()]
    elif isinstance(value, list) and all(isinstance(v, str) for v in value):
        items = [v.strip() for v in value]
    else:
        raise UsageError(f"{where}: expected a list of names, got {value!r}")
    if where.endswith("methods") and items == ["all"]:
        return available_methods()
    return items


def train_table_to_args(table: Mapping[str, Any], where: str = "[train]") -> list[str]:
    """``{"eval-every": 1000, "hidden": [256, 256], "quiet": True}`` → flags for ``mira train``."""
    args: list[str] = []
    for key, value in table.items():
        flag = "--" + str(key).replace("_", "-")
        if isinstance(value, bool):
            if value:
                args.append(flag)
        elif isinstance(value, int | float | str):
            args += [flag, str(value)]
        elif isinstance(value, list) and all(isinstance(v, int | float | str) for v in value):
            args += [flag, ",".join(str(v) for v in value)]
        else:
            raise UsageError(f"{where}: {key} has an unsupported value {value!r}")
    return args


def split_train_args(value: Any, where: str = "train_args") -> list[str]:
    if isinstance(value, str):
        try:
            return shlex.split(value)
        except ValueError as exc:
            raise UsageError(f"{where}: cannot split {value!r} ({exc})") from None
    if isinstance(value, list) and all(isinstance(v, str | int | float) and not isinstance(v, bool)
                                       for v in value):
        return [str(v) for v in value]
    raise UsageError(f"{where}: expected a string or a list of strings, got {value!r}")


# -------------------------------------------------------------------------------------- sweep files
def load_sweep_file(path: str | Path) -> dict[str, Any]:
    """Read and check a TOML or YAML sweep file; return its settings with values normalised.

    The result holds only the keys the file sets (``train`` and ``train_args`` merged into
    ``train_args``); task-card paths are resolved relative to the file.
    """
    file = Path(path)
    where = f"sweep file {file}"
    try:
        raw = file.read_bytes()
    except OSError as exc:
        raise UsageError(f"{where}: cannot read it ({exc.strerror or exc})") from None
    suffix = file.suffix.lower()
    data: Any
    if suffix == ".toml":
        try:
            data = tomllib.loads(raw.decode("utf-8"))
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
            raise UsageError(f"{where}: invalid TOML ({_one_line(exc)})") from None
    elif suffix in (".yaml", ".yml"):
        import yaml

        try:
            data = yaml.safe_load(raw.decode("utf-8"))
        except (yaml.YAMLError, UnicodeDecodeError) as exc:
            raise UsageError(f"{where}: invalid YAML ({_one_line(exc)})") from None
    else:
        raise UsageError(f"{where}: unsupported extension {file.suffix!r} (use .toml, .yaml or .yml)")
    if data is None:
        data = {}
    if not isinstance(data, dict):
        raise UsageError(f"{where}: the top level must be a table of keys, got {type(data).__name__}")
    if isinstance(data.get("sweep"), dict) and set(data) <= {"sweep", "train"}:
        # Also accept everything under a [sweep] table.
        data = {**data["sweep"], **({"train": data["train"]} if "train" in data else {})}
    unknown = sorted(set(data) - set(FILE_KEYS))
    if unknown:
        raise UsageError(f"{where}: unknown key {unknown[0]!r} (known: {', '.join(FILE_KEYS)})")
    out: dict[str, Any] = {}
    if "preset" in data:
        if not isinstance(data["preset"], str):
            raise UsageError(f"{where}: preset must be a string, got {data['preset']!r}")
        out["preset"] = data["preset"]
    for key in ("tasks", "methods", "algos"):
        if key in data:
            out[key] = parse_names(data[key], f"{where}: {key}")
    if "tasks" in out:
        out["tasks"] = [_resolve_task(t, file.parent) for t in out["tasks"]]
    if "programs" in data:
        out["programs"] = parse_programs(data["programs"], f"{where}: programs", file.parent)
    if "seeds" in data:
        out["seeds"] = parse_seeds(data["seeds"], f"{where}: seeds")
    for key in ("steps", "workers", "retries"):
        if key in data:
            value = data[key]
            minimum = 0 if key == "retries" else 1
            if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
                raise UsageError(f"{where}: {key} must be an integer >= {minimum}, got {value!r}")
            out[key] = value
    if "cpus_per_run" in data:
        value = data["cpus_per_run"]
        if isinstance(value, bool) or not isinstance(value, int | float) or value <= 0:
            raise UsageError(f"{where}: cpus_per_run must be a positive number, got {value!r}")
        out["cpus_per_run"] = value
    if "backend" in data:
        if data["backend"] not in ("pool", "ray"):
            raise UsageError(f"{where}: backend must be 'pool' or 'ray', got {data['backend']!r}")
        out["backend"] = data["backend"]
    if "address" in data:
        if not isinstance(data["address"], str):
            raise UsageError(f"{where}: address must be a string, got {data['address']!r}")
        out["address"] = data["address"]
    train_args: list[str] = []
    if "train" in data:
        if not isinstance(data["train"], dict):
            raise UsageError(f"{where}: train must be a table of flag = value, got {data['train']!r}")
        train_args += train_table_to_args(data["train"], f"{where}: [train]")
    if "train_args" in data:
        train_args += split_train_args(data["train_args"], f"{where}: train_args")
    if "train" in data or "train_args" in data:
        out["train_args"] = train_args
    try:  # check what the file names here, so that the error names the file
        if "train_args" in out:
            check_train_args(out["train_args"])
        for m in out.get("methods", []):
            check_method(m)
        for a in out.get("algos", []):
            check_algo(a)
        for t in out.get("tasks", []):
            check_task(t)
        if "programs" in out:
            check_programs(out["programs"])
    except UsageError as exc:
        raise UsageError(f"{where}: {exc}") from None
    return out


def _is_card(task: str) -> bool:
    return Path(task).suffix.lower() in (".toml", ".yaml", ".yml")


def _resolve_task(task: str, base: Path) -> str:
    path = Path(task)
    if path.suffix.lower() in (".toml", ".yaml", ".yml") and not path.is_absolute():
        candidate = base / path
        if candidate.exists():
            return str(candidate.resolve())
    return task


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def build_grid(*, preset: str | None = None, file: str | Path | None = None,
               overrides: Mapping[str, Any] | None = None) -> tuple[SweepGrid, dict[str, Any]]:
    """Merge preset < file < overrides into a checked grid and the execution settings.

    Each key of a later source replaces the earlier one, except ``train_args``, which are appended
    (so a later ``--eval-episodes 5`` overrides a preset's ``--eval-episodes 3``).

    ``overrides`` takes the same normalised keys as :func:`load_sweep_file` returns; ``None``
    values are ignored. Returns ``(grid, settings)`` where settings holds ``workers``, ``backend``,
    ``address``, ``cpus_per_run`` and ``retries`` when given.
    """
    from_file = load_sweep_file(file) if file is not None else {}
    given = {k: v for k, v in (overrides or {}).items() if v is not None}
    name = given.get("preset") or from_file.get("preset") or preset
    merged: dict[str, Any] = {}
    settings: dict[str, Any] = {}
    if name:
        base = preset_grid(name)
        merged.update({k: v for k, v in base.to_dict().items() if k != "preset"})
        settings.update(PRESET_SETTINGS.get(name, {}))
    for source in (from_file, given):
        for key, value in source.items():
            if key in SETTING_KEYS:
                settings[key] = value
            elif key == "train_args":  # appended: `mira train` takes the last value of a repeated flag
                merged["train_args"] = [*merged.get("train_args", []), *value]
            elif key != "preset":
                merged[key] = value
    missing = [k for k in ("tasks", "methods", "algos", "seeds", "steps") if k not in merged]
    if missing:
        raise UsageError(f"no {missing[0]} given (use --{missing[0]}, a sweep file or --preset)")
    # Task cards by absolute path: runs may start in another directory (a Ray worker's).
    tasks = [str(Path(t).resolve()) if _is_card(t) and Path(t).is_file() else t for t in merged["tasks"]]
    grid = SweepGrid(tasks, list(merged["methods"]), list(merged["algos"]),
                     list(merged["seeds"]), int(merged["steps"]), list(merged.get("train_args", [])),
                     preset=name or None, programs=list(merged.get("programs", [""])))
    return grid.validate(), settings
