"""TwoStageSAC, discrete soft actor-critic in two stages (paper Algorithm 1), and its policy.

The implementation details (every equation; the deviations from the paper and from the published code) are numbered in
``docs/implementation.md``; comments in the package cite them by number.
"""

from sb3_taskalloc.two_stage_sac.callbacks import SelectDAggerCallback
from sb3_taskalloc.two_stage_sac.entity_values import EntityValueDecoder, fit_entity_values
from sb3_taskalloc.two_stage_sac.policies import TAMPolicy
from sb3_taskalloc.two_stage_sac.settings import PAPER_KWARGS
from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC

__all__ = ["PAPER_KWARGS", "EntityValueDecoder", "SelectDAggerCallback", "TAMPolicy", "TwoStageSAC", "fit_entity_values"]
