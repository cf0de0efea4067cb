"""The embedded results store: SQLite (WAL), appended to by every invocation.

Schema (version 1):

- ``sessions``: one row per invocation, with provenance (suite, start time, git commit and
  dirty flag, machine, Python and package versions);
- ``runs``: one row per run with every ``runs.csv`` column and its session;
- ``series``: the windowed drift and energy series and sampled states of each run, one row
  per named array, stored as raw little-endian float64 bytes.

Each run is committed on its own, so a run that finished is never lost when a later one
crashes or the process is killed.
"""

from __future__ import annotations

import json
import platform
import sqlite3
import subprocess
import time
from importlib import metadata
from pathlib import Path

import numpy as np

from benchmarks.runner import COLUMNS, Record

SCHEMA_VERSION = 1
PACKAGES = ("numpy", "scipy", "jax", "jaxlib", "diffrax", "scikit-sundae", "pandas", "matplotlib")


def provenance() -> dict[str, object]:
    """Commit, dirty flag, machine and versions of the code that runs now."""
    root = Path(__file__).resolve().parent.parent

    def git(*args):
        try:
            return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True,
                                  timeout=10).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return ""

    versions = {}
    for name in PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = None
    return {
        "commit": git("rev-parse", "HEAD") or None,
        "dirty": bool(git("status", "--porcelain", "--untracked-files=no")),
        "machine": f"{platform.node()} {platform.machine()} {platform.processor()}".strip(),
        "python": platform.python_version(),
        "versions": json.dumps(versions),
    }


class Store:
    """Append-only access to ``driftbench.sqlite``."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.db = sqlite3.connect(self.path)
        self.db.execute("PRAGMA journal_mode=WAL")
        self.db.execute("PRAGMA synchronous=NORMAL")
        version = self.db.execute("PRAGMA user_version").fetchone()[0]
        if version == 0:
            self._create()
        elif version > SCHEMA_VERSION:
            raise RuntimeError(f"{self.path}: schema version {version} is newer than this "
                               f"code's ({SCHEMA_VERSION})")

    def _create(self) -> None:
        cols = ", ".join(f'"{c}"' for c in COLUMNS)
        with self.db:
            self.db.executescript(f"""
                CREATE TABLE IF NOT EXISTS sessions (
                    id INTEGER PRIMARY KEY, suite TEXT, started REAL, commit_sha TEXT,
                    dirty INTEGER, machine TEXT, python TEXT, versions TEXT);
                CREATE TABLE IF NOT EXISTS runs (
                    id INTEGER PRIMARY KEY, session INTEGER REFERENCES sessions(id), {cols});
                CREATE TABLE IF NOT EXISTS series (
                    run INTEGER REFERENCES runs(id), name TEXT, data BLOB,
                    PRIMARY KEY (run, name));
                PRAGMA user_version = {SCHEMA_VERSION};
            """)

    def begin(self, suite: str) -> int:
        """Open a session (one invocation) and return its id."""
        p = provenance()
        with self.db:
            cur = self.db.execute(
                "INSERT INTO sessions (suite, started, commit_sha, dirty, machine, python, versions)"
                " VALUES (?, ?, ?, ?, ?, ?, ?)",
                (suite, time.time(), p["commit"], int(p["dirty"]), p["machine"], p["python"],
                 p["versions"]))
        return cur.lastrowid

    def add(self, session: int, record: Record) -> int:
        """Append one finished run with its series, in one transaction."""
        cols = ", ".join(f'"{c}"' for c in COLUMNS)
        marks = ", ".join("?" for _ in COLUMNS)
        with self.db:
            cur = self.db.execute(f"INSERT INTO runs (session, {cols}) VALUES (?, {marks})",
                                  (session, *(record.row.get(c) for c in COLUMNS)))
            run = cur.lastrowid
            arrays = {f"window:{k}": v for k, v in record.windows.items()}
            arrays.update({f"sample:{k}": v for k, v in record.samples.items()})
            self.db.executemany(
                "INSERT INTO series (run, name, data) VALUES (?, ?, ?)",
                [(run, name, np.ascontiguousarray(a, dtype="<f8").tobytes())
                 for name, a in arrays.items()])
        return run
