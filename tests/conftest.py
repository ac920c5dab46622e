"""Test configuration: one thread everywhere (6× faster on small nets than oversubscribed BLAS on CI's 2 cores)."""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
# cuBLAS reads this when it starts: it lets the CUDA determinism check of test_save_load run (no effect on the CPU).
os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

import torch

import envs  # noqa: F401  (registers the TaskAlloc/* ids)

torch.set_num_threads(1)
