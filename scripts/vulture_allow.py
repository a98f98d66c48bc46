"""Names ``vulture src/mira`` calls unused that stay, each with its reason (vulture's whitelist format:
every name below counts as used).

    vulture src/mira scripts/vulture_allow.py --min-confidence 60    # run by scripts/test.sh

Anything vulture reports beyond these is dead code: delete it (with the tests that only exercise it), or,
where something outside ``src/mira`` reads it, add it here with the reason.
"""

import mira
import mira.api
from mira.baselines.synthetic import SyntheticEpisodes, linear_reward
from mira.factors.evaluator import FactorHealth
from mira.mcm.monitor import MetacognitiveMonitor
from mira.mcm.standardize import RobustStandardizer
from mira.shaping.networks import FactorAttentionBlock
from mira.shaping.testing import fill_episodes, make_hars
from mira.srr.efficacy import EfficacyReport

# Module protocol (PEP 562): the package's public names are imported on first use.
_ = mira.__getattr__, mira.__dir__

# Test support shipped with the package: synthetic episodes with a known per-step reward (the baselines'
# tests), and a bound HARS source filled with episodes (the shaping tests).
_ = SyntheticEpisodes.feed, linear_reward
_ = make_hars, fill_episodes

# Dataclass fields read by reflection: ``FactorHealth.to_dict`` (``vars``) and ``EfficacyReport.as_dict``
# (``asdict``, written into every SRR candidate's verdicts).
_ = FactorHealth.bad_shape, FactorHealth.nonfinite_values
_ = EfficacyReport.spearman_p

# Read by the monitor's benchmark (bench/mcm.py times them).
_ = MetacognitiveMonitor.raw_metrics, RobustStandardizer.smoothed

# The FAB as the paper writes it: the reference the fused forward is checked against (tests/test_shaping_networks.py).
_ = FactorAttentionBlock.reference

# The Python API (README, "Python API"): what mira.train returns, read by its callers.
_ = mira.api.TrainedRun.final_return
