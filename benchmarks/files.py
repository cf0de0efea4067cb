"""Files that are replaced whole: written beside their place under a unique temporary name,
then renamed over it.

A rename within one folder is atomic, so a reader sees the old file or the new one, never
a part of either; a writer that fails (a full disk, a kill) leaves the old file as it was
and no temporary file behind. The temporary name is unique to each write, so two
invocations writing the same file never write into each other's temporary file: the last
rename wins with a whole file.

This module imports neither JAX nor an integrator nor a problem.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


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
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
