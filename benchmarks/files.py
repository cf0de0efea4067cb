"""Files that are replaced whole (written beside their place under a unique temporary name,
then renamed over it), and the lock of an output folder.

A rename within one folder is atomic, so a reader sees the old file or the new one, never
a part of either; a writer that fails (a full disk, a kill) leaves the old file as it was
and no temporary file behind. The temporary name is unique to each write, so two
invocations writing the same file never write into each other's temporary file: the last
rename wins with a whole file.

This module imports neither JAX nor an integrator nor a problem.
"""

from __future__ import annotations

import fcntl
import os
import tempfile
from pathlib import Path


def new_file_mode(path) -> int:
    """The permissions a file at ``path`` gets: those of the file there now, else those of
    a file the process creates (``0o666`` less the umask).

    A unique temporary file is created private (``0o600``); the file renamed into place
    must not be.
    """
    try:
        return os.stat(path).st_mode & 0o7777
    except FileNotFoundError:
        umask = os.umask(0)
        os.umask(umask)
        return 0o666 & ~umask


def replace_file(path, content: str | bytes) -> None:
    """Write ``content`` to ``path`` atomically (text is written as UTF-8).

    Raises
    ------
    OSError
        When the content cannot be written (``ENOSPC`` on a full disk, ``EACCES``...):
        ``path`` is then as it was before the call.
    """
    path = Path(path)
    data = content.encode() if isinstance(content, str) else content
    fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(data)
        os.chmod(tmp, new_file_mode(path))
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


class FolderInUse(OSError):
    """Another process holds the lock of an output folder."""


class FolderLock:
    """An exclusive advisory lock on an output folder, held while one invocation writes it.

    The lock is ``fcntl.flock`` on ``FOLDER/.driftbench.lock``, which holds the process id
    of its holder (so the file is never empty and says who holds it). The kernel drops the
    lock when its holder ends, however it ends, so a killed invocation never leaves a stale
    lock; the file itself stays, which is harmless. Worker processes are started with
    ``exec``, which closes the descriptor, so they never hold the lock.

    Raises
    ------
    FolderInUse
        From :meth:`acquire`, when another process holds the lock; the message names it.
    """

    NAME = ".driftbench.lock"

    def __init__(self, folder):
        self.path = Path(folder) / self.NAME
        self.fd: int | None = None

    def acquire(self) -> None:
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 64, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise FolderInUse(f"{self.path.parent} is being written by another invocation "
                              f"(process {holder}); wait for it to end or give another "
                              f"--out") from None
        except BaseException:
            os.close(fd)
            raise
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self.fd = fd

    def release(self) -> None:
        if self.fd is not None:
            os.close(self.fd)  # closing the descriptor drops the lock
            self.fd = None
