"""pylsl, loaded only when Lab Streaming Layer is asked for (the optional extra ``rigctl[lsl]``; its wheel ships
liblsl): :func:`require_pylsl` returns the module or raises :class:`LslUnavailable` naming the fix. Shared by the
outlets (:mod:`rigctl.acquisition.lsl`) and the LSL replay source (:mod:`rigctl.simulation.lsl_replay`)."""

from __future__ import annotations

from typing import Any

__all__ = ["LslUnavailable", "require_pylsl"]


class LslUnavailable(RuntimeError):
    """LSL streaming was asked for but pylsl (or its liblsl) cannot be loaded."""


def require_pylsl() -> Any:
    """The pylsl module; :class:`LslUnavailable` in one line naming the fix when it (or liblsl) is missing."""
    try:
        import pylsl
    except (ImportError, RuntimeError, OSError) as exc:
        raise LslUnavailable(f"LSL streaming needs pylsl with its liblsl: pip install 'rigctl[lsl]' ({exc})") from None
    return pylsl
