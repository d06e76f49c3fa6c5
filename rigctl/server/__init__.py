"""rigctl.server: ``rigctl serve``'s HTTP API (FastAPI), a thin face on the operator layer's run queue
(:class:`rigctl.operations.RunQueue`) and rig control, as the CLI and the GUI are: no rig logic here; and its client
(:class:`ServerClient`, httpx only: the GUI attaches with it). docs/serve.md is the reference; the OpenAPI page is
served at ``/docs``. Names load lazily: the client never imports FastAPI."""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

_EXPORTS = {
    "create_app": "rigctl.server.app",
    "is_loopback": "rigctl.server.app",
    "ServerClient": "rigctl.server.client",
    "ServerError": "rigctl.server.client",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.server.app import create_app as create_app, is_loopback as is_loopback
    from rigctl.server.client import ServerClient as ServerClient, ServerError as ServerError
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
