"""HARS: the decomposed reward and the learned potential over typed reward factors (section 4.2.2).

Modules: ``config`` (hyperparameters), ``factors`` (what HARS needs from a program), ``columns``
(factor values of stored transitions), ``decomposition`` (r̂ fitted to episodic returns), ``memory``
(columns, statistics, episodes, σ_R and r̂ together), ``networks`` (FAB, VPM, TCE), ``objective`` (the
losses), ``potential`` (the networks, their optimiser step and the inputs Φ reads), ``beside`` (the
background thread), ``source`` (the reward source the trainer talks to).
Import from the modules themselves.
"""
