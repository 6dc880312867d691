"""Deprecated: the statistics moved to ``so101_sim.harness.stats`` (kept for one release)."""

import warnings

from so101_sim.harness.stats import *  # noqa: F403
from so101_sim.harness.stats import __all__  # noqa: F401

warnings.warn("so101_sim.stats is deprecated and will be removed in the next release; import "
              "from so101_sim.harness.stats", DeprecationWarning, stacklevel=2)
