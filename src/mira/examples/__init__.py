"""Example reward-factor programs (JSON) from the paper's case studies; load them with
:func:`mira.factors.example_program`."""
