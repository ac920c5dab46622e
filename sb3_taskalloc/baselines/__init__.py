"""Baselines with SB3's ``predict`` interface (DESIGN §6)."""

from sb3_taskalloc.baselines.base import Allocator
from sb3_taskalloc.baselines.greedy import GreedyAllocator, RandomAllocator
from sb3_taskalloc.baselines.milp import MILPAllocator, MILPSolution

__all__ = ["Allocator", "GreedyAllocator", "MILPAllocator", "MILPSolution", "RandomAllocator"]
