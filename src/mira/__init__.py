"""MIRA: metacognitive, LLM-driven reward design for sparse-reward reinforcement learning.

The package is laid out along the paper's modules and the data that flows between them::

    tasks/      task cards (named state features) and the episodic-reward environment wrapper
    factors/    typed reward-factor programs: model, static checker, sandbox, edit operators, LSFS
    llm/        LLM backends (OpenAI-compatible HTTP, scripted, offline rule-based) with an on-disk cache
    shaping/    HARS: factor attention, temporal context encoder, value potential, PBRS reward source
    agents/     SAC and DDPG (PyTorch), sharing networks
    rewards/    the reward-source interface and the simple sources (dense oracle, sparse episodic)
    baselines/  LaRe, RD, IRCR and VIB reward sources
    mcm/        metacognitive monitoring: diagnostics, KDE healthy model, trigger
    srr/        semantic reward reframing: evidence rules, prompt, candidate validation
    loop/       the one trainer, evaluation, and MIRA's outer loop
    runio/      run directories: atomic files, CSV logs, checkpoints
    experiments/ sweeps, metrics, reports
"""

__version__ = "0.1.0"
