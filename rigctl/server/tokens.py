"""``rigctl serve``'s token and where its clients find it (Jupyter's model): a token is always required; the server
generates one at start unless given, and writes it with its URL, mode 0600, beside its queue file
(``queue.json`` -> ``queue.token``, JSON ``{"url", "token", "pid"}``), where rigctl's own clients
(:class:`rigctl.server.ServerClient`, the GUI's attach window) read it. No FastAPI here: the client imports it.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
from pathlib import Path

from rigctl.storage.sidecars import write_small_file

__all__ = ["MIN_TOKEN_CHARS", "TokenError", "check_token", "default_queue_file", "default_data_dir", "new_token",
           "read_token_file", "remove_token_file", "token_file_for", "write_token_file"]

#: the shortest token the server takes, characters
MIN_TOKEN_CHARS = 16


class TokenError(ValueError):
    """A token the server refuses (blank, shorter than :data:`MIN_TOKEN_CHARS`, whitespace or control characters
    in it); one line."""


def check_token(token: str) -> str:
    """``token`` if the server takes it, else :class:`TokenError` saying why."""
    if not token or not token.strip():
        raise TokenError("the token is blank: give one of at least 16 characters (or none: one is generated)")
    if any(c.isspace() or ord(c) < 32 or ord(c) == 127 or ord(c) > 126 for c in token):
        raise TokenError("the token holds spaces, control or non-ASCII characters: use letters, digits and "
                         "punctuation")
    if len(token) < MIN_TOKEN_CHARS:
        raise TokenError(f"the token has {len(token)} characters: at least {MIN_TOKEN_CHARS} are required "
                         "(e.g. openssl rand -hex 16)")
    return token


def new_token() -> str:
    """A fresh random token (32 URL-safe characters)."""
    return secrets.token_urlsafe(24)


def default_queue_file() -> Path:
    """``$XDG_STATE_HOME/rigctl/queue.json`` (``~/.local/state/rigctl/queue.json``)."""
    state = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    return Path(state) / "rigctl" / "queue.json"


def default_data_dir() -> Path:
    """``$XDG_DATA_HOME/rigctl/sessions`` (``~/.local/share/rigctl/sessions``): where served runs write."""
    data = os.environ.get("XDG_DATA_HOME") or os.path.join(os.path.expanduser("~"), ".local", "share")
    return Path(data) / "rigctl" / "sessions"


def token_file_for(queue_file: str | os.PathLike[str]) -> Path:
    """The token file beside ``queue_file`` (same name, ``.token``)."""
    return Path(queue_file).with_suffix(".token")


def write_token_file(path: str | os.PathLike[str], *, url: str, token: str) -> Path:
    """Write ``{"url", "token", "pid"}`` to ``path``, mode 0600 from its creation (written aside, renamed)."""
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    # a sidecar of a random name, created new with mode 0600 (never a file or link already there), renamed over
    return write_small_file(p, json.dumps({"url": url, "token": token, "pid": os.getpid()}).encode(), mode=0o600,
                            exact_mode=True)


def read_token_file(path: str | os.PathLike[str], url: str | None = None) -> str | None:
    """The token in the token file ``path``, or None (no file, not readable, or written by a server at another
    ``url``: a token is never sent to a server it does not belong to)."""
    try:
        doc = json.loads(Path(path).read_text())
        token, file_url = doc["token"], doc.get("url")
    except (OSError, ValueError, KeyError, TypeError):
        return None
    if not isinstance(token, str):
        return None
    if url is not None and (not isinstance(file_url, str) or _origin(file_url) != _origin(url)):
        return None
    return token


def remove_token_file(path: str | os.PathLike[str], token: str) -> None:
    """Remove the token file if it still holds ``token`` (a newer server's file is left alone)."""
    p = Path(path)
    with contextlib.suppress(OSError, ValueError, KeyError, TypeError):
        if json.loads(p.read_text())["token"] == token:
            p.unlink()


def _origin(url: str) -> str:
    """``scheme://host:port`` of ``url``, lower case, ``localhost`` as 127.0.0.1, without a trailing slash."""
    from urllib.parse import urlsplit

    try:
        u = urlsplit(url.strip())
        port = u.port or (443 if u.scheme == "https" else 80)
    except ValueError:
        return url
    host = (u.hostname or "").lower()
    return f"{u.scheme.lower()}://{'127.0.0.1' if host == 'localhost' else host}:{port}"
