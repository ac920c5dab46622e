"""Optuna studies in a PostgreSQL database: workers started together share one study, and open it one at a time.

One module, so that one pytest-xdist worker runs its tests and starts the throw-away server once (``tests/conftest.py``).
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import optuna
import pytest

from tests.test_tuning import child_env, worker_args
from tuning import study as runner
from tuning.storage import schema_lock


@pytest.fixture(scope="module")
def postgres_url():
    """A throw-away PostgreSQL server (Debian's ``postgresql`` package), run as the ``postgres`` user on a Unix socket."""
    import glob
    import pwd
    import shutil

    bins = sorted(glob.glob("/usr/lib/postgresql/*/bin"))
    if not bins:
        pytest.skip("PostgreSQL server binaries not installed (Debian package postgresql; .ci/run installs it)")
    pytest.importorskip("psycopg", reason='the PostgreSQL driver is in the "tests" extra (psycopg[binary])')
    try:
        user = pwd.getpwnam("postgres")
    except KeyError:
        pytest.skip("no postgres system user to run the server as")
    folder = Path(tempfile.mkdtemp(prefix="taskalloc-pg-"))  # not under pytest's root-only folder: the server reads it
    data = folder / "data"
    os.chown(folder, user.pw_uid, user.pw_gid)

    def as_postgres(*cmd: str) -> None:
        runner = [] if os.getuid() == user.pw_uid else ["runuser", "-u", "postgres", "--"]
        subprocess.run([*runner, *cmd], check=True, capture_output=True, timeout=120)

    as_postgres(f"{bins[-1]}/initdb", "-D", str(data), "-A", "trust", "-U", "postgres")
    port = "54329"
    opts = f"-c listen_addresses='' -k {folder} -p {port}"
    as_postgres(f"{bins[-1]}/pg_ctl", "-D", str(data), "-o", opts, "-w", "-l", str(folder / "log"), "start")
    try:
        yield f"postgresql+psycopg://postgres@/postgres?host={folder}&port={port}"
    finally:
        as_postgres(f"{bins[-1]}/pg_ctl", "-D", str(data), "-m", "immediate", "stop")
        shutil.rmtree(folder, ignore_errors=True)


def test_two_workers_share_a_postgresql_study(tmp_path, postgres_url):
    env = child_env()
    args = [a if a != str(tmp_path / "s.log") else postgres_url for a in worker_args(tmp_path, 4)]
    workers = [
        subprocess.Popen([sys.executable, "-m", "tuning.study", *args], cwd=tmp_path, env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.STDOUT, text=True)
        for _ in range(2)
    ]  # fmt: skip
    for w in workers:
        out, _ = w.communicate(timeout=600)
        assert w.returncode == 0, out[-3000:]
    study = optuna.load_study(study_name="s", storage=postgres_url)
    finished = study.get_trials(states=runner.FINISHED)
    assert len(finished) == 4 and len({tuple(sorted(t.params.items())) for t in finished}) == 4
    assert isinstance(runner.make_storage(postgres_url, "s"), optuna.storages.RDBStorage)


def test_workers_wait_for_each_other_to_open_a_postgresql_study(postgres_url):
    """While one process holds the schema lock, another opening the storage waits for it in the server: workers starting
    together on an empty database create Optuna's tables one at a time (together, one of them failed with
    ``DuplicateTable``)."""
    import sqlalchemy

    opener = [sys.executable, "-c", f"from tuning.storage import make_storage; make_storage({postgres_url!r}, 'locked')"]
    waiting = sqlalchemy.text("SELECT count(*) FROM pg_locks WHERE locktype = 'advisory' AND NOT granted")
    engine = sqlalchemy.create_engine(postgres_url)
    try:
        with schema_lock(postgres_url), engine.connect() as connection:
            worker = subprocess.Popen(opener, env=child_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
            deadline = time.monotonic() + 120
            while connection.execute(waiting).scalar() == 0 and worker.poll() is None and time.monotonic() < deadline:
                time.sleep(0.1)
            assert worker.poll() is None, f"the worker opened the storage while the lock was held: {worker.communicate()[0]}"
            assert connection.execute(waiting).scalar() == 1
    finally:
        engine.dispose()
    out, _ = worker.communicate(timeout=120)
    assert worker.returncode == 0, out[-3000:]
