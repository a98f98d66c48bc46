"""The LLM-in-the-loop table: flawed HalfCheetah programs repaired with recorded LLM replies, beside the
offline rule-based engineer.

For each flaw and seed of each source (a folder laid out as ``bench/flawed.py``'s ``--out``): the SRR
exchanges of the ``mira`` run, whether the first reply was admitted, the replies sent back with the
checker's errors, whether an edit was installed, and the final return (mean evaluation return over the
final 10% of the budget). Per flaw and engineer: mean and [min, max] over seeds (fewer than 5 seeds: no
interval), how many seeds repaired the flaw (final return at least 70% of good-program ``hars``,
the flawed-program benchmark's criterion).

    python bench/llm/report.py --llm bench/archive/hc100_flawed_llm --offline bench/archive/hc100_flawed --steps 100000
"""

from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path
from typing import Any

import numpy as np

from mira.experiments.metrics import asymptotic_performance

FLAWS = ("no_progress", "abs_velocity", "wrong_gate", "saturated_velocity")
GOOD_HARS = 5374.0
"""Good-program ``hars`` on HalfCheetah at 100k, seeds 0–2 (``bench/archive/hc100_flawed``'s table)."""
REPAIRED = 0.70


def _jsonl(path: Path) -> list[dict[str, Any]]:
    if not path.is_file():
        return []
    return [json.loads(line) for line in path.read_text(encoding="utf-8").splitlines() if line.strip()]


def run_row(run: Path, steps: int) -> dict[str, Any] | None:
    eval_csv = run / "eval.csv"
    if not eval_csv.is_file():
        return None
    rows = list(csv.DictReader(eval_csv.open()))
    if not rows or int(rows[-1]["step"]) < steps:
        return None
    final = asymptotic_performance([float(r["step"]) for r in rows], [float(r["return_mean"]) for r in rows], steps)
    config = json.loads((run / "config.json").read_text())
    records = _jsonl(run / "llm" / "exchanges.jsonl")
    exchanges = [r for r in records if r.get("kind") == "exchange" and r.get("purpose") == "srr"]
    verdicts = {r["exchange_id"]: r["parse_result"] for r in records if r.get("kind") == "parse_result"}
    interventions = []
    for folder in sorted((run / "interventions").glob("*")):
        decision = json.loads((folder / "decision.json").read_text()) if (folder / "decision.json").is_file() else {}
        attempts = json.loads((folder / "attempts.json").read_text()) if (folder / "attempts.json").is_file() else None
        interventions.append({"step": int(folder.name.split("step")[-1]) if "step" in folder.name else None,
                              "operators": decision.get("operators") or [],
                              "reason": str(decision.get("reason", "")),
                              "accepted": bool(decision.get("accepted")),
                              "failed": bool(decision.get("failed")),
                              "turns": len(attempts) if attempts else 1,
                              "first_admitted": attempts[0]["admitted"] if attempts else None})
    first = [verdicts.get(e["id"], {}).get("admitted") for e in exchanges if
             verdicts.get(e["id"], {}).get("attempt") == 1]
    return {
        "engineer": config["config"]["llm"]["backend"],
        "final": final,
        "exchanges": len(exchanges),
        "first_admitted": sum(bool(a) for a in first),
        "first_asked": len(first),
        "sent_back": sum(1 for e in exchanges if verdicts.get(e["id"], {}).get("admitted") is False),
        "installed": sum(i["accepted"] for i in interventions),
        "failed": sum(i["failed"] for i in interventions),
        "interventions": interventions,
        "source": (config.get("environment") or {}).get("source"),
    }


def collect(root: Path, task: str, steps: int, seeds: list[int]) -> dict[tuple[str, int], dict[str, Any]]:
    out = {}
    for flaw in FLAWS:
        for seed in seeds:
            row = run_row(root / task / flaw / f"mira-sac-s{seed}", steps)
            if row is not None:
                out[(flaw, seed)] = row
    return out


def _summary(values: list[float]) -> str:
    if not values:
        return "—"
    return f"{np.mean(values):.0f} [{min(values):.0f}, {max(values):.0f}]"


def table(sources: dict[str, dict[tuple[str, int], dict[str, Any]]], seeds: list[int]) -> str:
    lines = ["| flaw | engineer | seeds | final return, mean [min, max] | repaired (≥ 70% of good hars) | "
             "SRR exchanges | first reply admitted | replies sent back | edits installed | interventions failed |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for flaw in FLAWS:
        for label, rows in sources.items():
            got = [rows[(flaw, s)] for s in seeds if (flaw, s) in rows]
            if not got:
                continue
            finals = [r["final"] for r in got]
            repaired = sum(f >= REPAIRED * GOOD_HARS for f in finals)
            installed = sum(r["installed"] for r in got)
            failed = sum(r["failed"] for r in got)
            if label == "offline":
                llm_cols = f"— | — | — | {installed} | {failed}"
            else:
                llm_cols = (f"{sum(r['exchanges'] for r in got)} | {sum(r['first_admitted'] for r in got)} of "
                            f"{sum(r['first_asked'] for r in got)} | {sum(r['sent_back'] for r in got)} | "
                            f"{installed} | {failed}")
            lines.append(f"| {flaw} | {label} | {len(got)} | {_summary(finals)} | {repaired} of {len(got)} | "
                         f"{llm_cols} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--llm", type=Path, required=True, help="folder of the runs with LLM replies")
    p.add_argument("--offline", type=Path, action="append", default=[],
                   help="folder(s) of the offline engineer's runs (the first holding a run is read)")
    p.add_argument("--task", default="halfcheetah")
    p.add_argument("--steps", type=int, default=100_000)
    p.add_argument("--seeds", default="0,1,2")
    args = p.parse_args(argv)
    seeds = [int(s) for s in args.seeds.split(",")]
    offline: dict[tuple[str, int], dict[str, Any]] = {}
    for root in args.offline:
        for key, row in collect(root, args.task, args.steps, seeds).items():
            offline.setdefault(key, row)
    llm = collect(args.llm, args.task, args.steps, seeds)
    print(table({"offline": offline, "LLM": llm}, seeds))
    print("\nPer run (final return: offline engineer → LLM; the LLM run's interventions):")
    for flaw in FLAWS:
        for seed in seeds:
            if (flaw, seed) not in llm:
                continue
            off = offline.get((flaw, seed))
            ivs = "; ".join(
                f"{i['step']}: " + ("installed " + "+".join(i["operators"]) if i["accepted"] else
                                    "failed (" + i["reason"][:60] + ")" if i["failed"] else "backed off")
                for i in llm[(flaw, seed)]["interventions"])
            before = "—" if off is None else f"{off['final']:.0f}"
            print(f"  {flaw} s{seed}: {before} → {llm[(flaw, seed)]['final']:.0f} ({ivs or 'no intervention'})")
    commits = sorted({str((r["source"] or {}).get("commit", "unrecorded"))[:7] if isinstance(r["source"], dict)
                      else str(r["source"])[:7] for r in [*offline.values(), *llm.values()]})
    print(f"\nRuns' recorded code: {', '.join(commits)}.")
    repaired = {label: sum(1 for f in FLAWS
                           if sum(rows[(f, s)]["final"] >= REPAIRED * GOOD_HARS for s in seeds if (f, s) in rows)
                           > len([s for s in seeds if (f, s) in rows]) / 2)
                for label, rows in (("offline", offline), ("LLM", llm))}
    print(f"Structural flaws repaired on a majority of seeds: offline {repaired['offline']} of 4, "
          f"LLM {repaired['LLM']} of 4.")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
