"""``python -m rigctl``: the ``rigctl`` command line (:mod:`rigctl.cli`)."""

from rigctl.cli import main, skip_exit_collections

if __name__ == "__main__":
    skip_exit_collections()
    main(prog_name="rigctl")
