"""LLM transport: how a request reaches whoever answers it, and what is kept of the exchange.

:mod:`.base` (requests, replies, the backend interface, typed errors), :mod:`.openai_backend` (any
OpenAI-compatible endpoint through the official SDK), :mod:`.script` (answers from a JSON Lines file),
and the layers every backend is wrapped in: :mod:`.cache` (responses on disk, keyed by the request),
:mod:`.budget` (a run's calls and tokens) and :mod:`.audit` (every exchange appended to the run
directory). What is asked, and the offline rule-based engineer that can answer instead of an LLM, are
in :mod:`mira.engineer`. Import from the modules themselves.
"""
