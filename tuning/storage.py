"""Where an Optuna study lives (:mod:`tuning.study`): a journal file, made safe to append to after a crash, or an RDB
URL with heartbeats."""

from __future__ import annotations

import contextlib
import json
import re
import time
import warnings
from collections.abc import Iterator
from pathlib import Path

import optuna
from optuna.storages.journal import JournalFileBackend, JournalFileOpenLock, JournalFileSymlinkLock
from optuna.storages.journal._storage import JournalOperation


def repair_journal(path: Path, lock: JournalFileSymlinkLock | JournalFileOpenLock) -> Path | None:
    """Make a journal file safe to append to, under the journal's own lock (so no worker is writing meanwhile).

    A last line without its newline is a record cut mid-write: it is moved to ``<path>.torn-<time>`` and cut off,
    because Optuna would append the next record onto it and leave a file it cannot read. Any other line that is not a
    JSON record (a damaged file, or not a journal at all) is refused with a clear error: nothing is written.

    :return: the file holding the cut-off bytes, or None when the journal was whole
    """
    if not path.exists() or path.stat().st_size == 0:
        return None
    while not lock.acquire():
        time.sleep(0.05)
    try:
        data = path.read_bytes()
        cut = data.rfind(b"\n") + 1
        whole, tail = data[:cut], data[cut:]
        hint = " (an SQLite database: use sqlite:///PATH)" if data.startswith(b"SQLite format 3") else ""
        lines = whole.splitlines()
        if tail and not tail.startswith(b"{"):  # not the start of a record, so not a record cut mid-write
            lines.append(tail)
        for number, line in enumerate(lines, 1):
            try:
                record = json.loads(line)
            except (UnicodeDecodeError, json.JSONDecodeError):
                raise ValueError(
                    f"{path} is not a readable Optuna journal{hint}: line {number} is not a JSON record; "
                    "nothing was written to it"
                ) from None
            op_code = record.get("op_code") if isinstance(record, dict) else None
            if op_code not in OP_CODES:  # Optuna's replay would stop at it with "AssertionError: Should not reach."
                raise ValueError(
                    f"{path}: line {number} has the operation code {op_code!r}, which this Optuna "
                    f"({optuna.__version__}) does not know (another version's journal, or not a journal); nothing was "
                    "written to it"
                )
        torn = None
        if tail:  # a record cut mid-write: keep its bytes aside, then cut it off
            torn = path.with_name(f"{path.name}.torn-{time.strftime('%Y%m%d-%H%M%S')}")
            torn.write_bytes(tail)
            with path.open("r+b") as f:
                f.truncate(cut)
        return torn
    finally:
        lock.release()


#: The operation codes of Optuna's journal records.
OP_CODES = frozenset(int(op) for op in JournalOperation)

#: A storage argument that starts like a URL (``name:``) without the ``//`` that SQLAlchemy URLs have.
_SCHEME = re.compile(r"^([A-Za-z][A-Za-z0-9+.-]+):(?!//)")


def make_storage(
    url: str | None, study_name: str, folder: str = "studies", heartbeat_interval: int = 30, grace_period: int = 120
) -> optuna.storages.BaseStorage:
    """The study's storage: a journal file (default ``<folder>/<study_name>.log``, or a path) repaired if its last
    record was cut (:func:`repair_journal`), or an RDB URL (``postgresql://…``, ``sqlite:///…``) with heartbeats and
    retries of failed trials.

    :param url: ``None``, a journal file path, or an SQLAlchemy URL
    :param study_name: study name (names the default journal file)
    :param folder: folder of the default journal file
    :param heartbeat_interval: seconds between heartbeats (RDB storage)
    :param grace_period: seconds without a heartbeat after which a running trial counts as dead (RDB storage)
    """
    check_storage_url(url)
    if url is None or "://" not in url:
        path = journal_path(url, study_name, folder)
        path.parent.mkdir(parents=True, exist_ok=True)
        lock = JournalFileSymlinkLock(str(path))
        torn = repair_journal(path, lock)
        if torn is not None:
            print(f"{path}: its last record was cut mid-write; moved it to {torn} and cut it off")
        return optuna.storages.JournalStorage(JournalFileBackend(str(path), lock_obj=lock))
    import sqlalchemy.exc

    for attempt in range(5):
        try:
            with warnings.catch_warnings(), schema_lock(url):  # heartbeats are an "experimental" argument of Optuna
                warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
                return optuna.storages.RDBStorage(
                    url,
                    heartbeat_interval=heartbeat_interval,
                    grace_period=grace_period,
                    heartbeat_stale_trial_callback=optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=2),
                )
        except (sqlalchemy.exc.IntegrityError, sqlalchemy.exc.OperationalError, sqlalchemy.exc.ProgrammingError) as error:
            # Workers starting together on a database without PostgreSQL's advisory locks race to create the schema:
            # the loser's CREATE fails ("already exists", a unique violation) and it retries, finding the tables made.
            if attempt == 4 or not (isinstance(error, sqlalchemy.exc.IntegrityError) or "already exists" in str(error)):
                raise
            time.sleep(0.5 * (attempt + 1))
    raise AssertionError("unreachable")  # the last attempt returns or raises


@contextlib.contextmanager
def schema_lock(url: str) -> Iterator[None]:
    """Hold a PostgreSQL session advisory lock while the storage opens, so that workers starting together create
    Optuna's tables and stamp its schema version one at a time; nothing is held for other databases.

    Optuna's table creation and Alembic's version stamp check whether a table exists, then create it: two workers on an
    empty database both pass the check and the second's ``CREATE TABLE alembic_version`` fails (``DuplicateTable``).

    :param url: the study's SQLAlchemy URL
    """
    import sqlalchemy

    if sqlalchemy.engine.make_url(url).get_backend_name() != "postgresql":
        yield
        return
    engine = sqlalchemy.create_engine(url)
    try:
        with engine.connect() as connection:
            connection.execute(sqlalchemy.text("SELECT pg_advisory_lock(:key)"), {"key": SCHEMA_LOCK_KEY})
            try:
                yield
            finally:
                connection.execute(sqlalchemy.text("SELECT pg_advisory_unlock(:key)"), {"key": SCHEMA_LOCK_KEY})
    finally:
        engine.dispose()


#: The advisory lock's key: any number the study's database uses for nothing else (ASCII "optunaSt", halved to fit a signed
#: 64-bit integer).
SCHEMA_LOCK_KEY = int.from_bytes(b"optunaSt", "big") >> 1


def check_storage_url(url: str | None) -> None:
    """A clear error for a storage argument that is neither a journal path nor a URL Optuna's RDB storage can open (an
    unknown scheme, a missing database driver, a URL without its ``//`` that would become a journal file)."""
    if url is None:
        return
    if _SCHEME.match(url):
        raise ValueError(f"storage {url!r} looks like a URL without '//' (sqlite:///PATH, postgresql://HOST/DB); a journal "
                         "file is given by its path")  # fmt: skip
    if "://" not in url:
        return
    import sqlalchemy
    import sqlalchemy.exc

    try:
        sqlalchemy.create_engine(url).dispose()  # no connection yet: it checks the scheme and loads the driver
    except sqlalchemy.exc.NoSuchModuleError:
        scheme = url.split("://")[0]
        raise ValueError(
            f"storage {url!r}: {scheme!r} is not a database SQLAlchemy knows (sqlite:///PATH, postgresql://…, "
            "mysql://…); a journal file is given by its path"
        ) from None
    except (ImportError, sqlalchemy.exc.ArgumentError) as error:
        raise ValueError(f"storage {url!r} cannot be opened: {error}") from error


def journal_path(url: str | None, study_name: str, folder: str) -> Path:
    """The journal file of a study: ``url`` when given, else ``<folder>/<study_name>.log``."""
    return Path(url) if url else Path(folder) / f"{study_name}.log"
