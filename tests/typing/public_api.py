"""What a user's type checker sees of rigctl's public API: checked by the project's mypy run (pyproject.toml's
``[tool.mypy] files``), never imported or run. Each public name has its real type, not ``Any``: ``assert_type``
fails on ``Any``, and a wrong call is an error (its ``type: ignore`` would otherwise be unused, which
``warn_unused_ignores`` reports)."""

from typing import assert_type

import rigctl
import rigctl.acquisition
import rigctl.analysis
import rigctl.encoding
import rigctl.storage
from rigctl.acquisition.rig import Rig
from rigctl.acquisition.runner import RunSummary
from rigctl.operations import RigControl
from rigctl.storage import Session, open_session


def _public_names_are_typed(rig: Rig, control: RigControl) -> None:
    assert_type(rigctl.open_rig("inprocess"), Rig)
    assert_type(rigctl.open_session("a.h5"), Session)
    assert_type(rigctl.storage.open_session("a.h5"), Session)
    assert_type(rigctl.open_control(), RigControl)
    protocol = rigctl.load_protocol("quick_check.toml")
    assert_type(rigctl.run_protocol(protocol, "a.h5", rig=rig), RunSummary)
    assert_type(rigctl.acquisition.run_protocol(protocol, "a.h5", rig=rig), RunSummary)
    assert_type(rigctl.encoding.EncodeParams(), rigctl.encoding.EncodeParams)
    assert_type(rigctl.analysis.CVParams(), rigctl.analysis.CVParams)


def _wrong_calls_are_errors() -> None:
    open_session(1, 2, 3, bogus=True)  # type: ignore[call-arg, arg-type]
    rigctl.open_session(1, 2, 3, bogus=True)  # type: ignore[call-arg, arg-type]
    rigctl.open_rig(42)  # type: ignore[arg-type]
    rigctl.open_control(42)  # type: ignore[arg-type]
    rigctl.open_control(bogus=True)  # type: ignore[call-arg]
    rigctl.open_control(seed="0", home=3)  # type: ignore[arg-type]
    rigctl.run_protocol()  # type: ignore[call-arg]
    rigctl.no_such_public_name  # type: ignore[attr-defined]  # noqa: B018
    rigctl.storage.no_such_public_name  # type: ignore[attr-defined]  # noqa: B018
