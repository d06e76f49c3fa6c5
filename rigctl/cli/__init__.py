"""The ``rigctl`` command line (click). Each command lives in its own module of this package, imported on use."""

from __future__ import annotations

import importlib

import click

from rigctl.core.version import __version__


def skip_exit_collections() -> None:
    """Have the interpreter's exit skip its cyclic garbage collections: ``gc.freeze()`` as an exit handler (every
    exit handler still runs; objects are still freed as their references go, and the OS takes the rest). Called by
    the ``rigctl`` entries (the console script, ``python -m rigctl``), not in-process runs (tests' CliRunner).

    The exit's collections walk every object the imports left (~160k with numpy, SciPy, scikit-learn, numba and h5py
    loaded: 0.17 CPU-s a collection on this machine) for none to free: a command's outputs are closed when it returns.
    Measured: importing what ``rigctl analyze`` imports and exiting, 4.2-4.5 -> 3.5-3.7 CPU-s (load ~20), the exit
    ~1.3 s of wall after Table 1's JSON at load 5 (docs/results.md 5 on issue 57 item 4)."""
    import atexit
    import gc

    atexit.register(gc.freeze)


#: the line a Ctrl-C ends a command with, where the command has nothing of its own to say (nothing to resume)
INTERRUPTED = "interrupted (Ctrl-C): no partial output was left; the inputs are unchanged"

#: command name -> "module:attribute" of the click command, imported only when the command runs
COMMANDS = {
    "acquire": "rigctl.cli.acquire:acquire",
    "info": "rigctl.cli.info:info",
    "ports": "rigctl.cli.ports:ports",
    "sim": "rigctl.cli.sim:sim",
    "encode": "rigctl.cli.encode:encode",
    "analyze": "rigctl.cli.analyze:analyze",
    "import": "rigctl.cli.import_recordings:import_recordings",
    "import-fabricslide": "rigctl.cli.fabricslide:import_fabricslide",
    "gui": "rigctl.cli.gui:gui",
    "export": "rigctl.cli.export:export",
    "protocols": "rigctl.cli.protocols:protocols",
    "firmware": "rigctl.cli.firmware:firmware",
    "doctor": "rigctl.cli.doctor:doctor",
    "calibrate": "rigctl.cli.calibrate:calibrate",
    "udev-rules": "rigctl.cli.udev:udev_rules",
    "serve": "rigctl.cli.serve:serve",
    "rigs": "rigctl.cli.rigs:rigs",
    "safety": "rigctl.cli.safety:safety",
}

SHORT_HELP = {
    "acquire": "Run an acquisition protocol on the rig and record a session file.",
    "info": "Summarise a session file, trial by trial.",
    "ports": "List serial ports and which rig board each looks like.",
    "sim": "Start the simulated rig, or generate a simulated dataset.",
    "encode": "Encode a session's trials into SA/RA spike trains.",
    "analyze": "Run the paper's PCA + LDA analyses on a session or dataset.",
    "import": "Import recordings of any sensor (CSV, NPY/NPZ, MAT, NWB, XDF) into a session file.",
    "import-fabricslide": "Import the FabricSlide recordings into a session file.",
    "gui": "Start the desktop app.",
    "export": "Export a session: NWB, spike events (Tonic's layout), a per-trial layout.",
    "protocols": "List the built-in protocols (run one by name).",
    "firmware": "Build the boards' firmware images from the installed sources (for flashing).",
    "doctor": "Bring-up checks on the rig: one line each, pass/fail/skip and the fix.",
    "calibrate": "Calibrate the rig: the load cell with a known mass (calibrate loadcell --mass-g G).",
    "udev-rules": "Print udev rules: stable /dev names for the boards by USB serial number.",
    "serve": "Headless run queue with an HTTP API (127.0.0.1 by default).",
    "rigs": "List the installed rigs (rigctl's own and plugins'), whether each loads.",
    "safety": "The host's safety rules: `rigctl safety table` prints them (markdown).",
}


def _quiet_broken_pipe() -> None:
    """Point stdout at /dev/null (so the interpreter's last flush cannot fail again) and exit 1 without a word,
    as https://docs.python.org/3/library/signal.html#note-on-sigpipe recommends."""
    import os
    import sys

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError):  # no real stdout (a test runner's buffer)
        pass
    raise SystemExit(1)


class SuggestingGroup(click.Group):
    """A command group whose unknown command names its nearest command ("did you mean"), as click does for options
    (click suggests nothing for commands: ``rigctl aquire`` said only "No such command")."""

    def resolve_command(self, ctx, args):
        try:
            return super().resolve_command(ctx, args)
        except click.UsageError:
            import difflib

            name = args[0] if args else ""
            close = difflib.get_close_matches(name, self.list_commands(ctx), n=1, cutoff=0.6)
            if not close or name.startswith("-"):
                raise
            raise click.UsageError(f"No such command {name!r}; did you mean {close[0]!r}?", ctx) from None


class LazyGroup(SuggestingGroup):
    def list_commands(self, ctx):
        return sorted(COMMANDS)

    def get_command(self, ctx, name):
        target = COMMANDS.get(name)
        if target is None:
            return None
        module, attr = target.split(":")
        try:
            return getattr(importlib.import_module(module), attr)
        except ModuleNotFoundError as exc:
            if exc.name == module:
                return None
            raise

    def invoke(self, ctx):
        """Run the command; an exception that escapes it becomes one line (:mod:`rigctl.cli.errors`) unless
        ``--debug``."""
        try:
            return super().invoke(ctx)
        except click.exceptions.NoArgsIsHelpError:  # a group with no command (`rigctl export`): its help, whole
            raise
        except click.UsageError as exc:  # one line too: click would add the usage and a 'Try --help' line
            from rigctl.cli.errors import one_line

            where = f" (see '{exc.ctx.command_path} --help')" if exc.ctx is not None else ""
            raise click.UsageError(one_line(exc.format_message()).rstrip(".") + where) from None
        except click.ClickException as exc:  # one line, values not numpy reprs, whoever built the message
            from rigctl.cli.errors import one_line

            exc.message = one_line(exc.message)
            raise
        except (click.exceptions.Exit, click.Abort):
            raise
        except KeyboardInterrupt:  # a command that has nothing to resume: its partial output is already removed
            raise click.ClickException(INTERRUPTED) from None
        except BrokenPipeError:  # `rigctl info X | head`: the reader has gone; end quietly (Python's recipe)
            _quiet_broken_pipe()
        except Exception as exc:
            if ctx.params.get("debug"):
                raise
            from rigctl.cli.interrupts import is_interrupt

            if is_interrupt(exc):  # a Ctrl-C that C code turned into its own error (rigctl.cli.interrupts)
                raise click.ClickException(INTERRUPTED) from None
            from rigctl.cli.errors import as_click_error

            raise as_click_error(exc) from exc

    def format_commands(self, ctx, formatter):
        rows = [(name, SHORT_HELP.get(name, "")) for name in self.list_commands(ctx)]
        with formatter.section("Commands"):
            formatter.write_dl(rows)


@click.group(cls=LazyGroup)
@click.version_option(__version__, prog_name="rigctl")
@click.option("--debug", is_flag=True, default=False, envvar="RIGCTL_DEBUG",
              help="Show the full traceback of an error (also RIGCTL_DEBUG=1).")
@click.option("--verbose", is_flag=True, default=False, envvar="RIGCTL_VERBOSE",
              help="Show the libraries' log records (pymodbus' retries and frames) on the terminal; without it they "
                   "go to the log file ($XDG_STATE_HOME/rigctl/rigctl.log, or $RIGCTL_LOG).")
def main(debug, verbose):
    """rigctl: run the tactile texture rig, record sessions, and reproduce the paper's analyses.

    The simulated rig is the default wherever a rig is needed (--sim). An error is reported as one line; --debug
    shows its traceback.

    Exit status: 0 done; 1 an error (a file, the rig, a failed check, Ctrl-C during work), nothing partial left; 2 a
    usage error (an option or argument refused before any work, named in the message).
    """
    from rigctl.cli.logs import route_library_logs

    route_library_logs(verbose)
