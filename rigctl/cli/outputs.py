"""Output files of the commands: checked before any long work starts, written so an existing file is never lost.

Every command that writes a file calls :func:`check_output` first (before the rig moves, before an analysis runs):
an existing file is refused without ``--overwrite``, an output that is also one of the command's inputs is refused
even with ``--overwrite`` (``rigctl encode X.h5 --out X.h5`` would replace the recording), an unsupported format is
refused by its extension, and the folder must exist and take a new file. Small outputs (CSV, plots, models) are
written through :func:`replacing`: into a temporary file beside the target, renamed over it when complete.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

import click

__all__ = ["UsageProblem", "check_output", "same_file", "replacing", "image_suffixes"]


class UsageProblem(click.ClickException):
    """A usage error shown as one line (``Error: ...``) with exit status 2, without click's usage banner."""

    exit_code = 2


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True if ``a`` and ``b`` name the same file: :func:`os.path.samefile` when both exist (hard links, symlinks),
    else the same resolved path."""
    a, b = Path(a), Path(b)
    try:
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    except OSError:
        pass
    return a.resolve() == b.resolve()


def image_suffixes() -> tuple[str, ...]:
    """Image extensions matplotlib writes (``.png``, ``.pdf``, ``.svg``, ...), lower case with the dot."""
    from matplotlib.figure import Figure

    return tuple(sorted("." + s for s in Figure().canvas.get_supported_filetypes()))


def check_output(path: str | os.PathLike, *, option: str = "--out", overwrite: bool = False,
                 inputs: Iterable[str | os.PathLike | None] = (), suffixes: Iterable[str] | None = None,
                 overwrite_hint: str = "pass --overwrite to replace it") -> Path:
    """Refuse an output path before any work starts; returns it as a Path.

    Parameters
    ----------
    path : the output file.
    option : the option that named it (for the message).
    overwrite : an existing file may be replaced.
    inputs : the command's input files (None entries are ignored): the output must be none of them.
    suffixes : allowed extensions (lower case, with the dot), or None for any.
    overwrite_hint : what to do about an existing file (e.g. "continue it with --resume, or pass --overwrite").

    Raises
    ------
    UsageProblem (exit 2), one line: the path is a folder, is one of the inputs, has an unsupported extension,
    exists without ``overwrite``, or its folder is missing or does not take a new file (read-only, no permission).
    """
    p = Path(path)
    if p.is_dir():
        raise UsageProblem(f"{option} {p} is a folder: give a file name")
    for inp in inputs:
        if inp is not None and same_file(p, inp):
            alias = f" ({inp})" if str(inp) != str(p) else ""
            raise UsageProblem(f"{option} {p} is one of the input files{alias}: choose another output file")
    if suffixes is not None:
        suffixes = tuple(suffixes)
        if p.suffix.lower() not in suffixes:
            raise UsageProblem(f"{option} {p}: unsupported format {p.suffix or '(no extension)'}; use one of "
                               f"{', '.join(suffixes)}")
    if p.exists() and not overwrite:
        raise UsageProblem(f"{option} {p} exists: {overwrite_hint}")
    check_writable_folder(p.parent if str(p.parent) else Path("."), option=option, target=p)
    return p


def check_writable_folder(folder: Path, *, option: str, target: Path | None = None) -> None:
    """Refuse a folder that does not exist or does not take a new file (tried with a temporary file, removed)."""
    what = f"{option} {target}" if target is not None else f"{option} {folder}"
    if not folder.is_dir():
        raise UsageProblem(f"{what}: the folder {folder} does not exist: create it or choose another")
    try:
        fd, probe = tempfile.mkstemp(prefix=".rigctl-write-check-", dir=folder)
    except OSError as exc:
        raise UsageProblem(f"{what}: cannot write in {folder} ({exc.strerror or exc}): choose another folder") from None
    os.close(fd)
    with contextlib.suppress(OSError):
        os.unlink(probe)


@contextlib.contextmanager
def replacing(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path`` (same extension); rename it over ``path`` when the block completes.

    An exception leaves ``path`` as it was and removes the temporary file."""
    p = Path(path)
    fd, tmp = tempfile.mkstemp(prefix=f".{p.stem}-", suffix=p.suffix, dir=p.parent if str(p.parent) else ".")
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


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
