"""The reward engineer: what MIRA asks for and how the answers are read, whoever gives them.

* LSFS (section 4.2.1): :mod:`.lsfs_prompt` builds the request from a task card and parses the reply
  strictly; :mod:`.lsfs` asks the configured backend and checks the program before anyone uses it.
* SRR (section 4.4): :mod:`.srr_prompt` turns the monitor's evidence into the request (Appendix A's
  layout), :mod:`.srr_candidates` parses the reply into candidate programs.
* :mod:`.backends` builds the backend a run uses (offline, ``script:FILE`` or ``openai:MODEL``) with
  the response cache, budget and audit log of :mod:`mira.llm`.
* The offline, rule-based engineer (:mod:`.offline`, :mod:`.offline_lsfs`, :mod:`.offline_srr`,
  :mod:`.factorcode`) answers the same requests without a network: deterministic, and named as what
  it is everywhere.
Prompt templates are text files under ``prompts/``.
"""
