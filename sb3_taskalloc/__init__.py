"""sb3_taskalloc: Stable-Baselines3 extension for dynamic multi-entity task allocation.

Importing it registers the env ids ``TaskAlloc/<Name>-v0`` (the ``envs`` package), so that
``TwoStageSAC("TAMPolicy", "TaskAlloc/RBF-v0")`` works as SB3 users write it.
"""

import envs  # noqa: F401  (registers the TaskAlloc ids)
from sb3_taskalloc.two_stage_sac import PAPER_KWARGS, SelectDAggerCallback, TAMPolicy, TwoStageSAC

__version__ = "0.1.0"

__all__ = ["PAPER_KWARGS", "SelectDAggerCallback", "TAMPolicy", "TwoStageSAC", "__version__"]
