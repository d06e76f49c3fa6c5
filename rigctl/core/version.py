"""The installed rigctl's version: its one home (``rigctl.__version__`` re-exports it; pyproject.toml's
``version`` is held equal by tests/test_public_api.py). Inside rigctl, import it from here, never from the root
package ``rigctl`` (the users' facade, which names every layer)."""

__version__ = "0.1.0"
