"""sb3_taskalloc: Stable-Baselines3 extension for dynamic multi-entity task allocation."""

__version__ = "0.1.0"
