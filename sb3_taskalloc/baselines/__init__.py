"""Baselines with SB3's ``predict`` interface (DESIGN §6)."""

from sb3_taskalloc.baselines.base import Allocator
from sb3_taskalloc.baselines.greedy import GreedyAllocator, RandomAllocator

__all__ = ["Allocator", "GreedyAllocator", "RandomAllocator"]
