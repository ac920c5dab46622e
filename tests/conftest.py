"""Test configuration: one thread everywhere (6× faster on small nets than oversubscribed BLAS on CI's 2 cores), and
the experiment runners' fixtures for shorter runs."""

import os
import shutil
import tempfile
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
# cuBLAS reads this when it starts: it lets the CUDA determinism check of test_save_load run (no effect on the CPU).
os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")

import gymnasium as gym
import pytest
import torch

import envs  # noqa: F401  (registers the TaskAlloc/* ids)
from tests.runner_helpers import SHORT_EPT_STEPS, short_worker

torch.set_num_threads(1)
# SB3 makes a log folder for every learn() without a logger of its own (``/tmp/SB3-<time>``, empty unless a format
# writes to it): the suite's thousands go to one folder, shared by the xdist workers and subprocesses, removed at the end.
_LOGS = None if "SB3_LOGDIR" in os.environ else os.environ.setdefault("SB3_LOGDIR", tempfile.mkdtemp(prefix="sb3-tests-"))


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """The ``slow`` learning checks run first where the rest of the suite runs too (a plain ``pytest -n 2``): the other
    workers run the rest beside them, instead of one worker running a several-minute check at the end while the others
    wait. ``make test`` leaves them out; ``make test-slow`` runs them alone."""
    items.sort(key=lambda item: item.get_closest_marker("slow") is None)


#: Test modules whose tests share an expensive session fixture: each one's tests go to a single pytest-xdist worker, so
#: that its fixture is computed once per run (under plain load balancing each worker that ran one of them computed it).
ONE_WORKER_MODULES = ("test_smoke_tables.py", "test_tuning_postgres.py")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config: pytest.Config, log: Any) -> Any:
    """``--dist load`` (what ``-n`` implies), except that each module of :data:`ONE_WORKER_MODULES` is one unit of work.
    xdist's own ``--dist loadgroup`` does this by ``xdist_group`` marks, but its marks do not reach the scheduler under
    pytest 9 (it renames a node id attribute that pytest 9 no longer reads)."""
    if config.getvalue("dist") != "load":
        return None
    from xdist.scheduler import LoadScopeScheduling

    class Scheduling(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return module if module.rsplit("/", 1)[-1] in ONE_WORKER_MODULES else nodeid

    return Scheduling(config, log)


def pytest_unconfigure(config: pytest.Config) -> None:
    if _LOGS is not None:
        shutil.rmtree(_LOGS, ignore_errors=True)


@pytest.fixture
def short_branching(monkeypatch: pytest.MonkeyPatch) -> None:
    """The learning experiment's diagnosis with 2 rollouts from every 20th state (8 from every 10th by default): the
    same figures, from fewer branches."""
    from functools import partial

    from sb3_taskalloc.experiments import diagnose

    monkeypatch.setattr(diagnose, "diagnose", partial(diagnose.diagnose, branches=2, branch_stride=20))


@pytest.fixture
def short_episodes() -> Any:
    """EPT episodes of :data:`SHORT_EPT_STEPS` steps, here and in the learning experiment's worker processes: the
    runners' plumbing (files, columns, resumption) is the same on an eighth of an episode (the report test: 127 s at
    100 steps, 42 s at 25, 23 s at 12). A MonkeyPatch of its own, so that a test's ``monkeypatch.undo()`` keeps it."""
    from sb3_taskalloc.experiments import learn

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(gym.spec("TaskAlloc/EPT-v0"), "max_episode_steps", SHORT_EPT_STEPS)
        patch.setattr(learn, "one_thread", short_worker)
        yield
