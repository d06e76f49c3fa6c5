"""Where rigctl keeps what it computes once and reuses: the user's cache folder, never the installed package.

numba writes the compiled kernels of ``@njit(cache=True)`` beside their sources by default; for an installed
package that is ``site-packages/rigctl/**/__pycache__``, which ``pip`` does not remove with the package, so a later
editable install of the same name (``pip install -e ".[docs]"``) finds a ``rigctl`` folder of cache files shadowing
it (issue 38). :func:`configure_numba_cache` points numba at ``$XDG_CACHE_HOME/rigctl/numba`` instead; ``import
rigctl`` calls it, before any kernel is defined.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path


def user_cache_root() -> Path:
    """``$XDG_CACHE_HOME/rigctl`` (default ``~/.cache/rigctl``): rigctl's folder in the user's cache."""
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "rigctl"


def numba_cache_dir() -> Path:
    """The folder numba keeps rigctl's compiled kernels in: ``$NUMBA_CACHE_DIR`` when set, else
    ``$XDG_CACHE_HOME/rigctl/numba`` (default ``~/.cache/rigctl/numba``)."""
    chosen = os.environ.get("NUMBA_CACHE_DIR")
    return Path(chosen) if chosen else user_cache_root() / "numba"


def configure_numba_cache() -> Path:
    """Send numba's kernel cache to :func:`numba_cache_dir` unless ``NUMBA_CACHE_DIR`` already says where.

    Sets ``NUMBA_CACHE_DIR`` in this process's environment (numba reads it when first imported; worker processes and
    CLI subprocesses inherit it) and, when numba was imported first, its loaded setting too. Creates no folder (numba
    does, at the first kernel it caches). Returns the folder.
    """
    path = numba_cache_dir()
    if not os.environ.get("NUMBA_CACHE_DIR"):
        os.environ["NUMBA_CACHE_DIR"] = str(path)
        config = getattr(sys.modules.get("numba.core.config"), "__dict__", None)
        if config is not None:  # numba came first: its cache locators read config.CACHE_DIR at each kernel's definition
            config["CACHE_DIR"] = str(path)
    return path
