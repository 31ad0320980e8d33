"""Writing output files safely: into a temporary file beside the target, then renamed over it.

A schedule, an instance, a scenario or a chart written straight into its target is destroyed by a failed write (a
full disk, a quota, an interrupt): the old content is gone and half a file is left. Written here, the target is
replaced only by a complete file (``os.replace`` is atomic on one file system), a failed write leaves the old file
as it was and removes its temporary, and a watcher of the folder never sees half a file.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from pathlib import Path
from typing import Iterator

__all__ = ["replacing", "write_atomically"]


@contextlib.contextmanager
def replacing(path: str | Path) -> Iterator[Path]:
    """A temporary path to write ``path``'s new content to; on leaving without an error it replaces ``path``
    (with the permissions a new file gets), on an error it is removed and ``path`` is left as it was. The parent
    folders are created."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    fd, name = tempfile.mkstemp(prefix=f".{out.name}.", suffix=".tmp", dir=str(out.parent))
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        mask = os.umask(0)
        os.umask(mask)
        os.chmod(tmp, 0o666 & ~mask)  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, out)
    except BaseException:
        with contextlib.suppress(OSError):
            tmp.unlink()
        raise


def write_atomically(path: str | Path, text: str) -> Path:
    """Write ``text`` (UTF-8) to ``path`` through :func:`replacing`; returns the path."""
    with replacing(path) as tmp:
        tmp.write_text(text, encoding="utf-8")
    return Path(path)
