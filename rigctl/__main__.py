"""``python -m rigctl``: the ``rigctl`` command line (:mod:`rigctl.cli`)."""

from rigctl.cli import main, skip_exit_collections
from rigctl.cli.interrupts import keep_ctrl_c

if __name__ == "__main__":
    skip_exit_collections()
    keep_ctrl_c()
    main(prog_name="rigctl")
