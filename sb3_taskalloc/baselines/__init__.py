"""Baselines with SB3's ``predict``: greedy, random, exact one-step MILP and receding-horizon planners."""

from sb3_taskalloc.baselines.base import Allocator
from sb3_taskalloc.baselines.greedy import GreedyAllocator, RandomAllocator
from sb3_taskalloc.baselines.milp import MILPAllocator
from sb3_taskalloc.baselines.planners import GeneticAlgorithm, ParticleSwarm, RecedingHorizonPlanner, SymbioticOrganismsSearch

__all__ = [
    "Allocator",
    "GeneticAlgorithm",
    "GreedyAllocator",
    "MILPAllocator",
    "ParticleSwarm",
    "RandomAllocator",
    "RecedingHorizonPlanner",
    "SymbioticOrganismsSearch",
]
