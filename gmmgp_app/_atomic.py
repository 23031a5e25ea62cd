"""Write outputs under a temporary sibling name and rename them when complete.

A crash, Ctrl-C or full disk never leaves a half-written file or folder under
the final name: either the old content or the new one is there.
"""

from __future__ import annotations

import os
import shutil
import uuid
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_path", "atomic_write_text", "atomic_dir"]


def _sibling(path: Path, suffix: str = "") -> Path:
    # Same folder, so os.replace is an atomic rename; created with the ordinary
    # umask (unlike mkstemp's private 0600 files). The suffix keeps the extension
    # for writers that insist on one (np.savez, Open3D).
    return path.parent / f".{path.name}.{os.getpid()}.{uuid.uuid4().hex[:8]}.tmp{suffix}"


@contextmanager
def atomic_path(path, suffix: str = ""):
    """``with atomic_path(p) as tmp: write(tmp)`` then ``tmp`` is renamed to ``p``."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path, suffix)
    try:
        yield tmp
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise


def atomic_write_text(path, text: str) -> Path:
    with atomic_path(path) as tmp:
        tmp.write_text(text)
    return Path(path)


@contextmanager
def atomic_dir(path):
    """``with atomic_dir(d) as tmp: fill(tmp)``; then ``tmp`` replaces ``d`` whole."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = _sibling(path)
    tmp.mkdir()
    try:
        yield tmp
        if path.exists():
            old = _sibling(path, ".old")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
