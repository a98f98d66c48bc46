"""Run directories: atomic files, append-only CSV logs, checkpoints with content hashes."""
