"""sb3_taskalloc: Stable-Baselines3 extension for dynamic multi-entity task allocation."""

from sb3_taskalloc.two_stage_sac import PAPER_KWARGS, SelectDAggerCallback, TAMPolicy, TwoStageSAC

__version__ = "0.1.0"

__all__ = ["PAPER_KWARGS", "SelectDAggerCallback", "TAMPolicy", "TwoStageSAC", "__version__"]
