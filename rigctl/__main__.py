"""``python -m rigctl``: the ``rigctl`` command line (:mod:`rigctl.cli`)."""

from rigctl.cli import main

if __name__ == "__main__":
    main(prog_name="rigctl")
