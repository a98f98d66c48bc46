"""Metacognitive Monitoring (MCM, section 4.3): per-cycle diagnostics, KDE healthy model, trigger.

The trainer feeds :class:`CycleSnapshot` values (plain NumPy) to :class:`MetacognitiveMonitor` and
acts on :class:`MCMResult`; the monitor never touches networks or the training loop.
"""

from mira.mcm.band import stagnation_band
from mira.mcm.config import MCMConfig
from mira.mcm.kde import HealthyModel, top_contributors
from mira.mcm.monitor import MetacognitiveMonitor
from mira.mcm.records import METRIC_NAMES, Contributor, CycleSnapshot, MCMResult, row_fields
from mira.mcm.standardize import RobustStandardizer

__all__ = [
    "METRIC_NAMES",
    "Contributor",
    "CycleSnapshot",
    "HealthyModel",
    "MCMConfig",
    "MCMResult",
    "MetacognitiveMonitor",
    "RobustStandardizer",
    "row_fields",
    "stagnation_band",
    "top_contributors",
]
