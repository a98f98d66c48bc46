"""The sandbox worker: a separate ``python -I`` process that runs factor code on real states.

Started by :mod:`mira.factors.sandbox`; never imported by anything else. Order of events:

1. import NumPy and the compiler and call every whitelisted function once (so nothing is loaded
   lazily later, when the file system is gone);
2. read the job (a pickle written by the trusted parent) from stdin;
3. lock itself down, each layer best-effort and reported back: no core files, ``RLIMIT_CPU``,
   ``RLIMIT_FSIZE = 0``, ``RLIMIT_AS`` (current size + budget), a fresh network namespace
   (``unshare(CLONE_NEWNET)``: no interfaces, so no network), ``chroot`` into the empty job
   directory and a switch to user ``nobody`` when started as root, ``PR_SET_NO_NEW_PRIVS``,
   ``RLIMIT_NPROC = 0`` (no fork) and finally ``RLIMIT_NOFILE = 0`` (no new file descriptor of
   any kind, so no open, socket or pipe);
4. for each factor: announce it, compile it (the static checker runs again inside
   ``compile_factor``), call it on the batches and write the raw outputs back as one JSON line
   (float64 bytes in base64). The parent, not the worker, computes every figure and verdict, and
   it never unpickles anything the worker sends.
"""

from __future__ import annotations

import base64
import contextlib
import ctypes
import json
import os
import pickle
import resource
import sys
import time
from typing import Any

import numpy as np

from mira.factors.compiler import InadmissibleCodeError, compile_factor
from mira.factors.whitelist import NP_PROXY, NUMPY_FUNCTIONS

_CLONE_NEWUSER = 0x10000000
_CLONE_NEWNET = 0x40000000
_PR_SET_NO_NEW_PRIVS = 38
_NOBODY = 65534


class _View:
    """Read-only batch of states: one attribute per feature plus ``obs``."""

    __slots__ = ("_values",)

    def __init__(self, values: dict[str, np.ndarray]) -> None:
        object.__setattr__(self, "_values", values)

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            values: dict[str, np.ndarray] = object.__getattribute__(self, "_values")
            return values[name]
        except KeyError:
            raise AttributeError(f"the state has no feature {name!r}") from None

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError("the state view is read-only")


def _emit(obj: dict[str, Any]) -> None:
    sys.stdout.write(json.dumps(obj) + "\n")
    sys.stdout.flush()


def _prewarm() -> None:
    x = np.linspace(0.1, 0.9, 8)
    with np.errstate(all="ignore"):
        for name, spec in NUMPY_FUNCTIONS.items():
            args: list[object] = [x] * spec.min_pos
            if spec.power_positions:
                args[1] = 2
            with contextlib.suppress(Exception):
                getattr(NP_PROXY, name)(*args)
        np.linalg.norm(np.ones((2, 2)), axis=-1)


def _vm_bytes() -> int:
    try:
        with open("/proc/self/status", encoding="ascii") as handle:
            for line in handle:
                if line.startswith("VmSize:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    return 512 * 1024 * 1024


def _lockdown(limits: dict[str, int], jail: str) -> list[str]:
    layers: list[str] = []

    def limit(which: int, value: int, label: str) -> None:
        try:
            resource.setrlimit(which, (value, value))
            layers.append(label)
        except (ValueError, OSError):
            pass

    limit(resource.RLIMIT_CORE, 0, "RLIMIT_CORE=0")
    cpu = int(limits["cpu_s"])
    try:
        resource.setrlimit(resource.RLIMIT_CPU, (cpu, cpu + 1))
        layers.append(f"RLIMIT_CPU={cpu}s")
    except (ValueError, OSError):
        pass
    limit(resource.RLIMIT_FSIZE, 0, "RLIMIT_FSIZE=0")
    vm = _vm_bytes() + int(limits["mem_bytes"])
    limit(resource.RLIMIT_AS, vm, f"RLIMIT_AS={vm // (1024 * 1024)}MiB")
    libc = ctypes.CDLL(None, use_errno=True)
    root = os.geteuid() == 0
    if libc.unshare(_CLONE_NEWNET) == 0:
        layers.append("netns")
    elif not root and libc.unshare(_CLONE_NEWUSER | _CLONE_NEWNET) == 0:
        layers.append("userns+netns")
    if root:
        try:
            os.chroot(jail)
            os.chdir("/")
            layers.append("chroot")
            os.setgroups([])
            os.setgid(_NOBODY)
            os.setuid(_NOBODY)
            layers.append("uid=nobody")
        except OSError:
            pass
    if libc.prctl(_PR_SET_NO_NEW_PRIVS, 1, 0, 0, 0) == 0:
        layers.append("no_new_privs")
    limit(resource.RLIMIT_NPROC, 0, "RLIMIT_NPROC=0")
    limit(resource.RLIMIT_NOFILE, 0, "RLIMIT_NOFILE=0")
    return layers


def _encode(value: Any) -> dict[str, Any]:
    arr = np.asarray(value)
    record: dict[str, Any] = {"shape": [int(n) for n in arr.shape], "dtype": str(arr.dtype), "data": None}
    if arr.dtype.kind in "fiub" and arr.size <= 1_000_000:
        raw = np.ascontiguousarray(arr, dtype="<f8").tobytes()
        record["data"] = base64.b64encode(raw).decode("ascii")
    return record


def _run_factor(
    spec: dict[str, Any], job: dict[str, Any], views: list[_View], halves: tuple[_View, _View]
) -> dict[str, Any]:
    name, kind = spec["name"], spec["type"]
    result: dict[str, Any] = {"event": "result", "factor": name, "status": "ok", "error": "", "outputs": {}}
    started = time.perf_counter()
    try:
        fn = compile_factor(name, kind, spec["code"], job["features"], _unchecked=bool(job.get("unchecked")))
    except InadmissibleCodeError as exc:
        result.update(status="inadmissible", error=str(exc)[:2000])
        return result
    actions = job["actions"]
    calls: list[tuple[str, _View, np.ndarray]] = [("base", views[0], actions)]
    calls.append(("half", halves[0], actions[: job["half"]]))
    calls.append(("single", halves[1], actions[:1]))
    calls.extend((f"dir{k}", view, actions) for k, view in enumerate(views[1:]))
    try:
        with np.errstate(all="ignore"):
            for label, view, acts in calls:
                out = fn(view) if kind != "AUX" else fn(view, acts)
                record = _encode(out)
                result["outputs"][label] = record
                if label == "base" and record["shape"] != [job["batch"]]:
                    break
    except MemoryError:
        result.update(status="memory", error="MemoryError")
    except Exception as exc:  # untrusted code: report, do not die
        result.update(status="error", error=f"{type(exc).__name__}: {exc}"[:2000])
    result["seconds"] = time.perf_counter() - started
    return result


def main() -> None:
    """Entry point (see the module docstring for the order of events)."""
    _prewarm()
    job = pickle.load(sys.stdin.buffer)  # written by the trusted parent
    views = []
    for values in job["batches"]:
        for arr in values.values():
            arr.setflags(write=False)
        views.append(_View(values))
    base = job["batches"][0]
    half = int(job["half"])
    halves = (_View({k: v[:half] for k, v in base.items()}), _View({k: v[:1] for k, v in base.items()}))
    job["actions"].setflags(write=False)
    layers = _lockdown(job["limits"], os.getcwd())
    _emit({"event": "ready", "isolation": layers})
    for spec in job["factors"]:
        _emit({"event": "start", "factor": spec["name"]})
        _emit(_run_factor(spec, job, views, halves))
    _emit({"event": "done"})


if __name__ == "__main__":
    main()
