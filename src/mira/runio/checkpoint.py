"""Checkpoints that are verified before use.

A checkpoint is ``ckpt-<step>.pt`` (a ``torch.save`` of a nested dict of tensors, arrays and plain
values) plus ``ckpt-<step>.json`` recording its SHA-256 and size. The payload is written first and
the manifest last, both atomically, so a checkpoint exists only once it is complete. ``load_latest``
walks back from the newest checkpoint and skips any whose hash does not match, reporting it.
"""

from __future__ import annotations

import hashlib
import io
import json
import logging
import os
from pathlib import Path
from typing import Any

import torch

from mira.errors import CheckpointError
from mira.runio.atomic import atomic_write_bytes, atomic_write_json
from mira.runio.failpoints import failpoint

log = logging.getLogger(__name__)

_PREFIX = "ckpt-"


def _payload_path(directory: Path, step: int) -> Path:
    return directory / f"{_PREFIX}{step:010d}.pt"


def _manifest_path(directory: Path, step: int) -> Path:
    return directory / f"{_PREFIX}{step:010d}.json"


def checkpoint_files(directory: str | os.PathLike[str], step: int) -> tuple[Path, Path]:
    """The payload and the manifest of the checkpoint of ``step`` in ``directory``."""
    return _payload_path(Path(directory), step), _manifest_path(Path(directory), step)


def save_checkpoint(directory: str | os.PathLike[str], step: int, state: dict[str, Any], keep: int = 2) -> Path:
    """Write a verified checkpoint for ``step`` and prune all but the newest ``keep``."""
    root = Path(directory)
    root.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    torch.save(state, buf)
    data = buf.getvalue()
    payload = _payload_path(root, step)
    failpoint("checkpoint.before_payload")
    atomic_write_bytes(payload, data)
    failpoint("checkpoint.after_payload")
    atomic_write_json(
        _manifest_path(root, step),
        {"step": step, "sha256": hashlib.sha256(data).hexdigest(), "bytes": len(data), "file": payload.name},
    )
    failpoint("checkpoint.after_manifest")
    for old in list_checkpoints(root)[:-keep] if keep > 0 else []:
        for path in (_payload_path(root, old), _manifest_path(root, old)):
            path.unlink(missing_ok=True)
    return payload


def list_checkpoints(directory: str | os.PathLike[str]) -> list[int]:
    """Steps of every checkpoint with a manifest, oldest first."""
    root = Path(directory)
    if not root.exists():
        return []
    steps = []
    for manifest in root.glob(f"{_PREFIX}*.json"):
        try:
            steps.append(int(manifest.stem[len(_PREFIX) :]))
        except ValueError:
            continue
    return sorted(steps)


def load_checkpoint(directory: str | os.PathLike[str], step: int) -> dict[str, Any]:
    """Load and verify the checkpoint of ``step``; raise ``CheckpointError`` if it is damaged."""
    root = Path(directory)
    manifest_file = _manifest_path(root, step)
    try:
        manifest = json.loads(manifest_file.read_text(encoding="utf-8"))
        data = _payload_path(root, step).read_bytes()
    except (OSError, json.JSONDecodeError) as exc:
        raise CheckpointError(f"checkpoint {step} in {root} is unreadable: {exc}") from exc
    digest = hashlib.sha256(data).hexdigest()
    if digest != manifest.get("sha256") or len(data) != manifest.get("bytes"):
        raise CheckpointError(f"checkpoint {step} in {root} fails its hash check (corrupt or truncated)")
    state: dict[str, Any] = torch.load(io.BytesIO(data), map_location="cpu", weights_only=False)
    return state


def load_latest(directory: str | os.PathLike[str]) -> tuple[int, dict[str, Any]] | None:
    """Newest checkpoint that verifies, or ``None`` if there is none; damaged ones are reported."""
    for step in reversed(list_checkpoints(directory)):
        try:
            return step, load_checkpoint(directory, step)
        except CheckpointError as exc:
            log.warning("%s; falling back to the previous checkpoint", exc)
    return None
