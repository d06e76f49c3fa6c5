"""rigctl.server: ``rigctl serve``'s HTTP API (FastAPI), a thin face on the operator layer's run queue
(:class:`rigctl.operations.RunQueue`) and rig control, as the CLI and the GUI are: no rig logic here.
docs/serve.md is its reference; the OpenAPI page is served at ``/docs``."""

from rigctl.server.app import create_app, is_loopback

__all__ = ["create_app", "is_loopback"]
