"""MIRA's outer loop (Algorithm 3): every ΔT steps the monitor (:mod:`mira.mcm`) reads held-out
rollouts; on a trigger SRR (:mod:`mira.srr`, asking :mod:`mira.engineer`) proposes and verifies edits,
and an accepted program goes back to HARS. It runs as a trainer hook (:mod:`mira.loop.hooks`)."""
