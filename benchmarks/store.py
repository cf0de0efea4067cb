"""The embedded results store: SQLite (WAL), appended to by every invocation.

Schema (version 6):

- ``sessions``: one row per invocation, with provenance (suite, start time, git commit and
  dirty flag, machine, Python and package versions, how wall times were kept honest);
- ``runs``: one row per run with every ``runs.csv`` column
  (:data:`benchmarks.records.COLUMNS`: the record is complete where the run happens, so
  the store never rebuilds a problem or an integrator), its session and the time it was
  recorded;
- ``series``: the windowed drift and energy series and sampled states of each run, and an
  ensemble's per-lane table (``lane:seed``, ``lane:status``, ``lane:max_pos_residual``...,
  one value per lane), one row per named array (``window:pos``, ``sample:q``...), stored as
  raw little-endian float64 bytes with the array's shape;
- ``artifacts``: tables and SVG figures of study suites that produce no runs, by session,
  report section and name.

Each run is committed on its own, so a run that finished is never lost when a later one
crashes or the process is killed. Older schema versions are migrated (in place by a
writer, in memory by a reader, which never modifies the file), so every reader sees the
current schema and data whatever code wrote them: nothing downstream asks how old a
store is.

Identity and integrity: the file carries SQLite's ``application_id``
(:data:`APPLICATION_ID`) and the schema version in ``user_version``. Every open, by a
writer or a reader, first checks (without writing) that the file is an SQLite database, that
it is ours and that ``PRAGMA quick_check`` passes; a damaged, truncated or foreign file is
refused with one line (:class:`DamagedStore`, :class:`ForeignFile`) that names it and how to
recover, and it is never written to. Stores written before the application id was set
(``application_id`` 0) are ours when they hold our tables; a writer sets the id when it
opens one.

A new store is built under a unique temporary name in its folder and linked into place
whole, so no empty or half-created store is ever left at the path (an empty file there is
refused as truncated).

Readers: :func:`load_runs` and :func:`load_artifacts` (pandas DataFrames),
:func:`load_series` (NumPy arrays) and :func:`load_lanes` (an ensemble's lanes, a DataFrame).
Readers open the file read-only, and where that cannot work (a read-only folder, where
SQLite cannot make the shared-memory file of write-ahead logging) as immutable, so the
report reads a store it cannot write. Reading imports neither JAX nor an integrator, so the
report stage stays light.
"""

from __future__ import annotations

import json
import os
import sqlite3
import tempfile
import time
from pathlib import Path
from typing import Callable

import numpy as np
import pandas as pd

from benchmarks.files import new_file_mode
from benchmarks.records import COLUMNS, TEXT_COLUMNS, WHOLE_COLUMNS, Record, Status, provenance

SCHEMA_VERSION = 6
STORE_NAME = "driftbench.sqlite"
#: Statuses of runs that a resumed suite must run again.
UNFINISHED = (Status.ERROR, Status.TIMEOUT)
#: Session columns joined onto every run by :func:`load_runs` (stored name -> loaded name).
SESSION_COLUMNS = {"suite": "suite", "started": "session_started", "commit_sha": "commit",
                   "dirty": "dirty", "machine": "machine", "python": "python",
                   "versions": "versions", "timing_note": "timing_note"}
#: Session columns read as text (with :data:`~benchmarks.records.TEXT_COLUMNS`); every
#: other column whose values are numbers (or missing) is read as float64, so a metric that
#: no run measured is NaN, not None.
SESSION_TEXT = set(SESSION_COLUMNS.values()) - {"session_started", "dirty"}


#: SQLite ``application_id`` of a driftbench store (``DRFT``), read by ``file(1)`` too.
APPLICATION_ID = 0x44524654
#: Tables a store of any version holds: how a store written before the application id was
#: set is told from another program's SQLite file.
OUR_TABLES = frozenset({"sessions", "runs", "series"})
#: Columns of those tables that every version has (version 1's), which readers rely on.
CORE_COLUMNS = {"sessions": ("id", "suite"),
                "runs": ("id", "session", "problem", "integrator", "status"),
                "series": ("run", "name", "data")}
#: The first 16 bytes of every SQLite database file.
SQLITE_MAGIC = b"SQLite format 3\x00"
#: What every refusal of a file says to do about it.
RECOVER = ("it was left as it is: move it aside (or restore a backup) to start a new store "
           "there, or give another --out")


class StoreError(RuntimeError):
    """A store that cannot be opened: missing, written by newer code, damaged or foreign."""


class DamagedStore(StoreError):
    """A store file that is truncated or whose pages fail SQLite's checks."""


class ForeignFile(StoreError):
    """A file at a store's path that is not a driftbench store (another program's)."""


# --------------------------------------------------------------------------- schema

def _create(db: sqlite3.Connection, columns) -> None:
    """Create the current schema in an empty database."""
    cols = ", ".join(f'"{c}"' for c in columns)
    db.executescript(f"""
        CREATE TABLE sessions (
            id INTEGER PRIMARY KEY, suite TEXT, started REAL, commit_sha TEXT,
            dirty INTEGER, machine TEXT, python TEXT, versions TEXT, timing_note TEXT);
        CREATE TABLE runs (
            id INTEGER PRIMARY KEY, session INTEGER REFERENCES sessions(id),
            recorded REAL, {cols});
        CREATE TABLE series (
            run INTEGER REFERENCES runs(id), name TEXT, data BLOB, shape TEXT,
            PRIMARY KEY (run, name));
        CREATE TABLE artifacts (
            id INTEGER PRIMARY KEY, session INTEGER REFERENCES sessions(id),
            section TEXT, name TEXT, kind TEXT, content TEXT, created REAL,
            UNIQUE (session, section, name, kind));
        PRAGMA user_version = {SCHEMA_VERSION};
    """)


def _v1_to_v2(db: sqlite3.Connection) -> None:
    """Version 1 -> 2: series shapes; record time, nominal order and sensitivity of runs;
    the timing note of sessions; artifacts.

    Version 1 stored every array flat, so the 2-D samples ``sample:q`` and ``sample:v``
    get their shape back from the length of the run's ``sample:t``. Rows of version 1
    have no record time, nominal order or sensitivity (NULL): the migration does not
    rebuild integrators or problems.
    """
    db.executescript("""
        ALTER TABLE series ADD COLUMN shape TEXT;
        ALTER TABLE runs ADD COLUMN recorded REAL;
        ALTER TABLE runs ADD COLUMN nominal_order REAL;
        ALTER TABLE runs ADD COLUMN sensitive INTEGER;
        ALTER TABLE sessions ADD COLUMN timing_note TEXT;
        CREATE TABLE artifacts (
            id INTEGER PRIMARY KEY, session INTEGER REFERENCES sessions(id),
            section TEXT, name TEXT, kind TEXT, content TEXT, created REAL,
            UNIQUE (session, section, name, kind));
    """)
    sizes = {(run, name): n // 8 for run, name, n in
             db.execute("SELECT run, name, length(data) FROM series")}
    for (run, name), size in sizes.items():
        shape = [size]
        if name in ("sample:q", "sample:v"):
            n_t = sizes.get((run, "sample:t"), 0)
            if n_t and size % n_t == 0:
                shape = [n_t, size // n_t]
        db.execute("UPDATE series SET shape = ? WHERE run = ? AND name = ?",
                   (json.dumps(shape), run, name))
    db.execute("PRAGMA user_version = 2")


def _v2_to_v3(db: sqlite3.Connection) -> None:
    """Version 2 -> 3: every column, every whole number an integer, every timing spread.

    Files of version 2 were written by code that knew fewer ``runs.csv`` columns (and,
    while version 2 was developed, fewer session columns): the columns they lack are added,
    empty. Whole-number columns hold integers (a count read back as ``10.0`` would be
    written to ``runs.csv`` as such). Runs recorded before the spread of their timed solves
    was get it from their one known time: the median of one solve, which is how the report
    showed them.
    """
    wanted = {"sessions": {"timing_note": "TEXT"},
              "runs": {"recorded": "REAL", **{c: "" for c in COLUMNS}}}
    for table, columns in wanted.items():
        have = set(_table_columns(db, table))
        for column, kind in columns.items():
            if column not in have:
                db.execute(f'ALTER TABLE {table} ADD COLUMN "{column}" {kind}')
    for column in WHOLE_COLUMNS:
        whole = f'CAST("{column}" AS INTEGER)'
        db.execute(f'UPDATE runs SET "{column}" = {whole} '
                   f'WHERE typeof("{column}") = \'real\' AND "{column}" = {whole}')
    db.execute("UPDATE runs SET wall_min_s = wall_s, wall_max_s = wall_s, repeats = 1 "
               "WHERE wall_s IS NOT NULL AND (wall_min_s IS NULL OR wall_max_s IS NULL)")
    db.execute("PRAGMA user_version = 3")


def _add_columns(db: sqlite3.Connection, version: int) -> None:
    """Add the columns of :data:`COLUMNS` that ``runs`` lacks (empty for the runs it holds)
    and mark the schema ``version``."""
    have = set(_table_columns(db, "runs"))
    for column in COLUMNS:
        if column not in have:
            db.execute(f'ALTER TABLE runs ADD COLUMN "{column}"')
    db.execute(f"PRAGMA user_version = {version}")


def _add_declared(db: sqlite3.Connection) -> None:
    """Add, empty, the declared columns (:data:`COLUMNS`) that ``runs`` lacks: a column
    declared after the file was written (:mod:`benchmarks.columns`) is empty for the runs
    it holds, as every migration that added columns made them. Done by name, not by schema
    version, since files of one version were written by code that declared different
    columns."""
    have = set(_table_columns(db, "runs"))
    missing = [c for c in COLUMNS if c not in have]
    if missing:
        with db:
            for column in missing:
                db.execute(f'ALTER TABLE runs ADD COLUMN "{column}"')


def _v3_to_v4(db: sqlite3.Connection) -> None:
    """Version 3 -> 4: the ensemble columns (``lanes``, ``seed``, ``batched``, the
    quantiles), empty for the single runs that version 3 held."""
    _add_columns(db, 4)


def _v4_to_v5(db: sqlite3.Connection) -> None:
    """Version 4 -> 5: an ensemble's ``chunks`` and the ``device`` a run ran on, empty for
    the runs that version 4 held."""
    _add_columns(db, 5)


def _v5_to_v6(db: sqlite3.Connection) -> None:
    """Version 5 -> 6: the quantiles of an ensemble's final errors (``final_q...``), empty
    for the runs that version 5 held. An ensemble's ``final_state_error``, ``scd`` and
    ``reference_floor`` are emptied too: in version 5 they were lane 0's, since the other
    lanes had no reference, and from version 6 on they are the worst lane's, so that the
    history would otherwise compare lane 0 with the worst lane and find a regression."""
    _add_columns(db, 6)
    db.execute("UPDATE runs SET final_state_error = NULL, scd = NULL, "
               "reference_floor = NULL WHERE lanes IS NOT NULL")


#: version -> the function that upgrades a database of that version by one.
MIGRATIONS: dict[int, Callable[[sqlite3.Connection], None]] = {
    1: _v1_to_v2, 2: _v2_to_v3, 3: _v3_to_v4, 4: _v4_to_v5, 5: _v5_to_v6}


def _version(db: sqlite3.Connection) -> int:
    return db.execute("PRAGMA user_version").fetchone()[0]


def migrate(db: sqlite3.Connection, where: str) -> None:
    """Upgrade ``db`` to :data:`SCHEMA_VERSION`, one version per transaction."""
    version = _version(db)
    if version > SCHEMA_VERSION:
        raise StoreError(f"{where}: schema version {version} is newer than this code's "
                         f"({SCHEMA_VERSION}); update driftbench to read it")
    while version < SCHEMA_VERSION:
        if version not in MIGRATIONS:
            raise StoreError(f"{where}: no migration from schema version {version}")
        with db:
            MIGRATIONS[version](db)
        version = _version(db)


def _table_columns(db: sqlite3.Connection, table: str) -> list[str]:
    return [row[1] for row in db.execute(f'PRAGMA table_info("{table}")')]


# --------------------------------------------------------------------------- identity

def _connect_read_only(path: Path) -> sqlite3.Connection:
    """A connection that cannot write ``path``: ``mode=ro``, else ``immutable=1``.

    A read-only open of a write-ahead-logged database needs its shared-memory file, which
    SQLite cannot make in a read-only folder; an immutable open needs none but does not
    see a write-ahead log, so it is refused while a non-empty one lies beside the file.
    """
    uri = path.resolve().as_uri()
    con = sqlite3.connect(uri + "?mode=ro", uri=True, timeout=30.0)
    try:
        con.execute("PRAGMA schema_version").fetchone()
        return con
    except sqlite3.OperationalError as exc:
        con.close()
        if "unable to open" not in str(exc) and "readonly" not in str(exc):
            raise
    wal = path.with_name(path.name + "-wal")
    if wal.exists() and wal.stat().st_size > 0:
        raise StoreError(f"{path}: cannot be read where it is (a read-only folder) while its "
                         f"write-ahead log {wal.name} holds runs; copy the folder somewhere "
                         f"writable and read the copy")
    return sqlite3.connect(uri + "?immutable=1", uri=True, timeout=30.0)


#: Files that passed :func:`identify`, by path and state: readers open a store once per
#: run's series, and ``quick_check`` reads the whole file.
_CHECKED: dict[tuple, int] = {}


def _state(path: Path) -> tuple:
    """What changes when a store or its write-ahead log is written."""
    wal = path.with_name(path.name + "-wal")
    stats = [path.stat(), *([wal.stat()] if wal.exists() else [])]
    return (str(path.resolve()), *((st.st_size, st.st_mtime_ns) for st in stats))


def identify(path) -> int:
    """Check that ``path`` is a sound driftbench store without writing to it; return its
    ``application_id`` (:data:`APPLICATION_ID`, or 0 for a store written before it was
    set).

    Raises
    ------
    DamagedStore
        An empty (truncated) file, one that SQLite cannot read or whose ``PRAGMA
        quick_check`` fails, or one that lacks a table or column of :data:`CORE_COLUMNS`.
    ForeignFile
        A file that is not SQLite, or an SQLite file of another program (another
        application id, or none and not our tables).
    """
    path = Path(path)
    try:
        state = _state(path)
    except OSError as exc:
        raise StoreError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if state in _CHECKED:
        return _CHECKED[state]
    try:
        with open(path, "rb") as fh:
            header = fh.read(len(SQLITE_MAGIC))
    except OSError as exc:
        raise StoreError(f"{path}: cannot be read: {exc.strerror or exc}") from None
    if not header:
        raise DamagedStore(f"{path}: damaged results store (the file is empty: truncated); "
                           f"{RECOVER}")
    if header != SQLITE_MAGIC:
        raise ForeignFile(f"{path}: not a driftbench results store (not an SQLite file); "
                          f"{RECOVER}")
    try:
        con = _connect_read_only(path)
        try:
            app = con.execute("PRAGMA application_id").fetchone()[0]
            tables = {r[0] for r in con.execute("SELECT name FROM sqlite_master "
                                                "WHERE type = 'table'")}
            if app != APPLICATION_ID and (app != 0 or not OUR_TABLES <= tables):
                what = (f"application id {app:#x}" if app else
                        f"its tables are {', '.join(sorted(tables)) or 'none'}")
                raise ForeignFile(f"{path}: not a driftbench results store (an SQLite file "
                                  f"of another program: {what}); {RECOVER}")
            for table, columns in CORE_COLUMNS.items():
                lacks = f"table {table}" if table not in tables else next(
                    (f"column {table}.{c}" for c in columns
                     if c not in _table_columns(con, table)), None)
                if lacks:
                    raise DamagedStore(f"{path}: damaged results store (no {lacks}); "
                                       f"{RECOVER}")
            problems = [r[0] for r in con.execute("PRAGMA quick_check")]
        finally:
            con.close()
    except sqlite3.DatabaseError as exc:
        raise DamagedStore(f"{path}: damaged results store (SQLite: {exc}); "
                           f"{RECOVER}") from None
    if problems != ["ok"]:
        raise DamagedStore(f"{path}: damaged results store (quick_check: {problems[0]}"
                           f"{f' and {len(problems) - 1} more' if len(problems) > 1 else ''}"
                           f"); {RECOVER}")
    _CHECKED[state] = app
    return app


def _create_file(path: Path, columns) -> None:
    """Build a new store under a unique temporary name beside ``path`` and link it into
    place; a store that another process put there meanwhile is kept."""
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    os.close(fd)
    try:
        os.chmod(tmp, new_file_mode(path))
        db = sqlite3.connect(tmp)
        try:
            with db:
                _create(db, columns)
            db.execute(f"PRAGMA application_id = {APPLICATION_ID}")
            db.execute("PRAGMA journal_mode=WAL")
        finally:
            db.close()
        try:
            os.link(tmp, path)  # unlike a rename, never replaces a store made meanwhile
        except FileExistsError:
            pass
    finally:
        for leftover in (tmp, f"{tmp}-wal", f"{tmp}-shm", f"{tmp}-journal"):
            Path(leftover).unlink(missing_ok=True)


# --------------------------------------------------------------------------- writer

class Store:
    """Append-only access to a results store (``driftbench.sqlite``).

    Opening creates the file (:func:`_create_file`), or checks an existing one
    (:func:`identify`: a damaged or foreign file raises before anything is written),
    migrates an older one in place (:func:`migrate`) and sets the application id of a
    store written before it was set.

    Raises
    ------
    StoreError
        A file that is refused (:class:`DamagedStore`, :class:`ForeignFile`), written by
        newer code, or that cannot be created (the message says why, on one line).
    """

    def __init__(self, path: Path):
        self.columns = COLUMNS
        self.path = Path(path)
        try:
            if not self.path.exists():
                _create_file(self.path, self.columns)
            app = identify(self.path)
            self.db = sqlite3.connect(self.path, timeout=30.0)
        except sqlite3.Error as exc:
            raise StoreError(f"{self.path}: cannot create or open the results store: "
                             f"{exc}") from None
        try:
            self._open(app)
        except BaseException:
            self.db.close()
            raise

    def _open(self, app: int) -> None:
        """Set the connection up and migrate the schema."""
        self.db.execute("PRAGMA journal_mode=WAL")
        # WAL with synchronous=NORMAL keeps every committed transaction through a crash
        # of the process; only a power loss may drop the last ones.
        self.db.execute("PRAGMA synchronous=NORMAL")
        migrate(self.db, str(self.path))
        _add_declared(self.db)
        if app != APPLICATION_ID:
            with self.db:
                self.db.execute(f"PRAGMA application_id = {APPLICATION_ID}")

    def close(self) -> None:
        self.db.close()

    def __enter__(self) -> "Store":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def begin(self, suite: str, timing_note: str | None = None) -> int:
        """Open a session (one invocation) and return its id.

        ``timing_note`` says how the runner kept wall times honest (shown by the report).
        """
        p = provenance()
        with self.db:
            cur = self.db.execute(
                "INSERT INTO sessions (suite, started, commit_sha, dirty, machine, python, "
                "versions, timing_note) VALUES (?, ?, ?, ?, ?, ?, ?, ?)",
                (suite, time.time(), p["commit"], int(p["dirty"]), p["machine"], p["python"],
                 p["versions"], timing_note))
        return cur.lastrowid

    def add(self, session: int, record: Record) -> int:
        """Append one finished run with its series, in one transaction; return its run id."""
        cols = ", ".join(f'"{c}"' for c in self.columns)
        marks = ", ".join("?" for _ in self.columns)
        with self.db:
            cur = self.db.execute(
                f"INSERT INTO runs (session, recorded, {cols}) VALUES (?, ?, {marks})",
                (session, time.time(), *record.row.values()))
            run = cur.lastrowid
            arrays = {f"window:{k}": v for k, v in record.windows.items()}
            arrays.update({f"sample:{k}": v for k, v in record.samples.items()})
            arrays.update({f"lane:{k}": v for k, v in record.lanes.items()})
            rows = []
            for name, a in arrays.items():
                a = np.ascontiguousarray(a, dtype="<f8")
                rows.append((run, name, a.tobytes(), json.dumps(list(a.shape))))
            self.db.executemany("INSERT INTO series (run, name, data, shape) VALUES (?, ?, ?, ?)",
                                rows)
        return run

    def add_table(self, session: int, section: str, name: str, table: pd.DataFrame) -> None:
        """Store a table of a study (report section ``section``); replaces a same-named one."""
        split = table.to_dict(orient="split")
        content = json.dumps({"columns": [str(c) for c in split["columns"]],
                              "index": split["index"], "data": split["data"]}, default=str)
        self._artifact(session, section, name, "table", content)

    def add_figure(self, session: int, section: str, name: str, svg_text: str) -> None:
        """Store an SVG figure of a study (report section ``section``)."""
        if "<svg" not in svg_text:
            raise ValueError(f"figure {section}/{name}: not SVG text")
        self._artifact(session, section, name, "figure", svg_text)

    def _artifact(self, session, section, name, kind, content) -> None:
        with self.db:
            self.db.execute(
                "INSERT OR REPLACE INTO artifacts (session, section, name, kind, content, created)"
                " VALUES (?, ?, ?, ?, ?, ?)", (session, section, name, kind, content, time.time()))

    def finished_keys(self) -> set[str]:
        """``run_key`` of every stored run that a resumed suite need not run again.

        A run is finished unless its status is ``error`` or ``timeout``.
        """
        marks = ", ".join("?" for _ in UNFINISHED)
        rows = self.db.execute(
            f"SELECT DISTINCT run_key FROM runs WHERE run_key IS NOT NULL "
            f"AND status NOT IN ({marks})", UNFINISHED)
        return {r[0] for r in rows}


    def finished(self, keys: set[str]) -> dict[str, Record]:
        """The latest finished stored run of each of ``keys``, as a :class:`Record`
        without its series (what ``runs.csv`` of a resumed batch lists)."""
        cols = ", ".join(f'"{c}"' for c in self.columns)
        marks = ", ".join("?" for _ in UNFINISHED)
        cursor = self.db.execute(
            f"SELECT {cols} FROM runs WHERE status NOT IN ({marks}) ORDER BY id", UNFINISHED)
        latest = {}
        for values in cursor:
            row = dict(zip(self.columns, values))
            if row["run_key"] in keys:
                latest[row["run_key"]] = Record.from_row(row)
        return latest


# --------------------------------------------------------------------------- readers

def _reader(db) -> sqlite3.Connection:
    """A read-only connection at the current schema version (migrated in memory if older)."""
    path = Path(db)
    if not path.exists():
        raise StoreError(f"{path}: no results store")
    identify(path)
    try:
        con = _connect_read_only(path)
    except sqlite3.Error as exc:
        raise StoreError(f"{path}: cannot be read: {exc}") from None
    try:
        if _version(con) < SCHEMA_VERSION:
            memory = sqlite3.connect(":memory:")
            con.backup(memory)
            con.close()
            con = memory
        migrate(con, str(path))
    except BaseException:
        con.close()  # a refused store's connection too
        raise
    return con


def load_runs(db) -> pd.DataFrame:
    """Every stored run with its session's provenance, one row per run.

    Columns: ``run_id``, ``session``, ``recorded``, every ``runs.csv`` column
    (``sensitive``: 1 for a chaotic problem, 0 if not, missing if unknown), and ``suite``,
    ``session_started``, ``commit``, ``dirty``, ``machine``, ``python``, ``versions``,
    ``timing_note`` from the session. Missing values are NaN (in number columns) or None.
    """
    con = _reader(db)
    try:
        provenance_cols = ", ".join(f's."{k}" AS "{v}"' for k, v in SESSION_COLUMNS.items())
        frame = pd.read_sql_query(
            f"SELECT r.*, {provenance_cols} FROM runs r LEFT JOIN sessions s "
            f"ON r.session = s.id ORDER BY r.id", con)
    finally:
        con.close()
    for column in frame.columns:
        if column in TEXT_COLUMNS or column in SESSION_TEXT or frame[column].dtype != object:
            continue  # pandas already typed it (ids stay integers)
        values = frame[column].dropna()
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in values):
            frame[column] = frame[column].astype("float64")
    return frame.rename(columns={"id": "run_id"})


def load_series(db, run_id: int) -> dict[str, dict[str, np.ndarray]]:
    """The arrays of one run: ``{"windows": {...}, "samples": {...}, "lanes": {...}}``.

    ``windows`` holds ``t`` (window end times), ``pos``, ``vel``, ``energy`` and
    ``inv:NAME`` (per-window maxima; for an ensemble, the maxima over its lanes and their
    medians ``median:NAME``); ``samples`` holds ``t``, ``q`` and ``v``; ``lanes`` an
    ensemble's per-lane table (:attr:`benchmarks.records.Record.lanes`; empty for a single
    run), which :func:`load_lanes` gives as a DataFrame.
    """
    con = _reader(db)
    try:
        rows = con.execute("SELECT name, data, shape FROM series WHERE run = ?",
                           (int(run_id),)).fetchall()
    finally:
        con.close()
    out: dict[str, dict[str, np.ndarray]] = {"windows": {}, "samples": {}, "lanes": {}}
    groups = {"window": "windows", "sample": "samples", "lane": "lanes"}
    for name, data, shape in rows:
        kind, _, key = name.partition(":")
        try:
            array = np.frombuffer(data, dtype="<f8").astype(np.float64)
            if shape:
                array = array.reshape(json.loads(shape))
            out[groups[kind]][key] = array
        except (KeyError, TypeError, ValueError) as exc:
            raise DamagedStore(f"{db}: damaged results store (series {name!r} of run "
                               f"{run_id}: {type(exc).__name__}: {exc}); {RECOVER}") from None
    return out


def load_lanes(db, run_id: int) -> pd.DataFrame:
    """An ensemble's per-lane table: one row per lane, columns ``seed`` (the lane's index,
    which with the run's seed draws its initial state), ``status`` (0 ok, 1 failed), the
    lane's metrics, ``t_final``, ``fail_step`` and ``fail_time`` (NaN where the lane
    finished; stores written before these columns lack them) and its work counters. Empty
    for a single run."""
    lanes = load_series(db, run_id)["lanes"]
    frame = pd.DataFrame(lanes)
    for column in ("seed", "status", "n_steps", "n_rejected", "n_f_evals", "n_jac_evals",
                   "n_newton", "n_lin_solves"):
        if column in frame:
            frame[column] = frame[column].astype("int64")
    return frame


def load_artifacts(db) -> pd.DataFrame:
    """Every stored study table and figure: ``session, section, name, kind, content, created,
    commit``.

    ``content`` is SVG text for figures; tables decode with :func:`artifact_table`.
    """
    con = _reader(db)
    try:
        return pd.read_sql_query(
            "SELECT a.session, a.section, a.name, a.kind, a.content, a.created, "
            "s.commit_sha AS \"commit\" FROM artifacts a LEFT JOIN sessions s "
            "ON a.session = s.id ORDER BY a.id", con)
    finally:
        con.close()


def artifact_table(content: str) -> pd.DataFrame:
    """Decode a stored study table."""
    split = json.loads(content)
    return pd.DataFrame(split["data"], index=split["index"], columns=split["columns"])
