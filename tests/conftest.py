"""Test configuration: one thread everywhere (6× faster on small nets than oversubscribed BLAS on CI's 2 cores)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
# cuBLAS reads this when it starts: it lets the CUDA determinism check of test_save_load run (no effect on the CPU).
os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

import pytest
import torch

import envs  # noqa: F401  (registers the TaskAlloc/* ids)

torch.set_num_threads(1)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The ``slow`` learning checks run first: under pytest-xdist (``make test``) the other workers run the rest of the
    suite beside them, instead of one worker running a several-minute check at the end while the others wait."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)
