from sb3_taskalloc.two_stage_sac.policies import TAMPolicy
from sb3_taskalloc.two_stage_sac.two_stage_sac import TwoStageSAC

__all__ = ["TAMPolicy", "TwoStageSAC"]
