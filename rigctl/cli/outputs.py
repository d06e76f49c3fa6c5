"""Output files of the commands: the library's one output policy (:mod:`rigctl.storage.outputs`), its refusals shown
as usage errors.

Every command that writes a file calls :func:`check_output` first (before the rig moves, before an analysis runs):
an existing file is refused without ``--overwrite``, an output that is also one of the command's inputs is refused
even with ``--overwrite`` (``rigctl encode X.h5 --out X.h5`` would replace the recording), a file another writer
holds (a session being recorded) is refused even with ``--overwrite``, an unsupported format is refused by its
extension, the folder must exist and take a new file, and an output estimated larger than the free space is
refused. Small outputs (CSV, plots, models) are written through :func:`replacing` (temporary file, renamed over the
target under its writer lock, mode per the umask).
"""

from __future__ import annotations

import os
import re
from collections.abc import Iterable
from pathlib import Path

import click

from rigctl.storage import outputs as _policy
from rigctl.storage.outputs import HDF5_SUFFIXES, replacing, same_file

__all__ = ["HDF5_SUFFIXES", "UsageProblem", "check_output", "same_file", "replacing", "image_suffixes"]


class UsageProblem(click.ClickException):
    """A usage error shown as one line (``Error: ...``) with exit status 2, without click's usage banner."""

    exit_code = 2


def image_suffixes() -> tuple[str, ...]:
    """Image extensions matplotlib writes (``.png``, ``.pdf``, ``.svg``, ...), lower case with the dot."""
    from matplotlib.figure import Figure

    return tuple(sorted("." + s for s in Figure().canvas.get_supported_filetypes()))


def check_output(path: str | os.PathLike, *, option: str = "--out", overwrite: bool = False,
                 inputs: Iterable[str | os.PathLike | None] = (), suffixes: Iterable[str] | None = None,
                 overwrite_hint: str = "pass --overwrite to replace it", need_bytes: float | None = None,
                 kind: str | None = None) -> Path:
    """:func:`rigctl.storage.outputs.check_output`, its refusal raised as :class:`UsageProblem` (exit 2)."""
    try:
        return _policy.check_output(path, option=option, overwrite=overwrite, inputs=inputs, suffixes=suffixes,
                                    overwrite_hint=overwrite_hint, need_bytes=need_bytes, kind=kind)
    except _policy.OutputError as exc:
        raise UsageProblem(str(exc)) from None


def check_writable_folder(folder: Path, *, option: str, target: Path | None = None) -> None:
    """:func:`rigctl.storage.outputs.check_writable_folder` as a usage error."""
    try:
        _policy.check_writable_folder(folder, option=option, target=target)
    except _policy.OutputError as exc:
        raise UsageProblem(str(exc)) from None


def require_dask(scheduler: object, *, otherwise: str) -> None:
    """Refuse ``--scheduler`` up front (:class:`UsageProblem`, exit 2) when Dask's distributed scheduler is not
    installed; ``otherwise`` ends the message (what to do instead, e.g. "encode in this process"). None passes."""
    if scheduler is None:
        return
    import importlib.util

    try:
        found = importlib.util.find_spec("dask.distributed") is not None
    except ModuleNotFoundError:  # dask itself is missing
        found = False
    if not found:
        raise UsageProblem("--scheduler needs Dask (dask.distributed), which is not installed: "
                           f"pip install 'rigctl[dask]', or drop --scheduler to {otherwise}")


_ADDRESS = re.compile(r"^(?:(?:tcp|tls|ucx|ws|wss)://)?(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9][A-Za-z0-9.\-]*)"
                      r"(?::(?P<port>\d{1,5}))?/?$")


def scheduler_address(ctx: click.Context, param: click.Parameter, value: str | None) -> str | None:
    """The ``--scheduler`` callback: ``local``, or a Dask scheduler address (``tcp://host:8786``, ``host:8786``);
    anything else is a usage error (exit 2) naming the option, before any work."""
    if value is None:
        return None
    text = value.strip()
    if text.lower() == "local":
        return "local"
    m = _ADDRESS.match(text)
    if m is None or (m.group("port") is not None and not 0 < int(m.group("port")) <= 65535) or (
            "://" not in text and m.group("port") is None):
        raise click.BadParameter(f"{value!r} is neither 'local' nor a Dask scheduler address such as "
                                 "tcp://127.0.0.1:8786")
    return text
