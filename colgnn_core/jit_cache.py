"""Where numba keeps its compiled kernels: a folder per version of the package's sources.

numba's on-disk cache (``@njit(cache=True)``) checks only the source file of the function it loads. A cached
function that calls a kernel from another module has that kernel compiled into it, and keeps the old one after that
module changes: after ``collision/kernels.py`` changed, ``self_contact._candidates`` ran the previous kernels from
its cache (2.4 ms a step compiled afresh, 4.4 ms from the stale cache, and the old code's results). So the cache
lives in a folder named by a hash of every module's path, size and modification time: any edit, pull or upgrade
starts a fresh folder. A user's own ``NUMBA_CACHE_DIR`` wins.

Nothing here imports numba; :func:`use_source_keyed_cache` must run before numba reads its configuration, which is
why the package's ``__init__`` calls it.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
from pathlib import Path

KEEP = 3  # cache folders kept besides the current one (other checkouts or versions in use on the machine)


def source_key(root: Path) -> str:
    """16 hex digits from the relative path, size and mtime (ns) of every ``*.py`` file under ``root``."""
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        st = path.stat()
        h.update(f"{path.relative_to(root)}\0{st.st_size}\0{st.st_mtime_ns}\n".encode())
    return h.hexdigest()[:16]


def user_cache(name: str) -> Path:
    """``$XDG_CACHE_HOME/colgnn/<name>`` (default ``~/.cache/colgnn/<name>``): the package's caches on disk."""
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "colgnn" / name


def cache_base() -> Path:
    """``$XDG_CACHE_HOME/colgnn/numba`` (default ``~/.cache/colgnn/numba``)."""
    return user_cache("numba")


def use_source_keyed_cache(root: Path, base: Path | None = None) -> Path | None:
    """Point numba's cache at ``base/<source_key(root)>`` unless ``NUMBA_CACHE_DIR`` is set; returns the folder
    (None when the user's setting stands or no folder can be made: numba then keeps its default)."""
    if os.environ.get("NUMBA_CACHE_DIR"):
        return None
    base = cache_base() if base is None else base
    folder = base / source_key(root)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError:
        return None
    os.environ["NUMBA_CACHE_DIR"] = str(folder)
    config = sys.modules.get("numba.core.config")
    if config is not None:  # numba was imported before us: its configuration has been read already
        config.CACHE_DIR = str(folder)
    _prune(base, folder)
    return folder


def _prune(base: Path, current: Path) -> None:
    """Remove all but the ``KEEP`` most recently modified folders besides ``current``."""
    try:
        others = sorted((p for p in base.iterdir() if p.is_dir() and p != current),
                        key=lambda p: p.stat().st_mtime, reverse=True)
    except OSError:
        return
    for old in others[KEEP:]:
        shutil.rmtree(old, ignore_errors=True)
