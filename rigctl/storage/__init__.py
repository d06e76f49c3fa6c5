"""rigctl.storage: every file format (h5py; layouts in ``docs/session-format.md``).

Public API (re-exported here, imported on first use): session files (``SessionWriter``, ``open_session`` ->
``Session``, ``SessionError``), encoded files (``EncodedWriter``, ``open_encoded`` -> ``EncodedFile``,
``NotEncodedError``, the variant registry ``VARIANTS``), importers (``import_recordings``, ``ImportOptions``, ``import_fabricslide``),
the NWB export (``export_nwb``) and model files (``save_model``, ``load_model``, ``ModelFileError``).
"""

from typing import TYPE_CHECKING

from rigctl.core.lazy import lazy_exports

#: the package's public names and the module each lives in
_EXPORTS = {
    "EncodedFile": "rigctl.storage.encoded",
    "EncodedWriter": "rigctl.storage.encoded",
    "NotEncodedError": "rigctl.storage.encoded",
    "VARIANTS": "rigctl.storage.encoded",
    "open_encoded": "rigctl.storage.encoded",
    "import_fabricslide": "rigctl.storage.fabricslide",
    "ImportOptions": "rigctl.storage.importers",
    "import_recordings": "rigctl.storage.importers",
    "ModelFileError": "rigctl.storage.model_file",
    "load_model": "rigctl.storage.model_file",
    "save_model": "rigctl.storage.model_file",
    "export_nwb": "rigctl.storage.nwb",
    "read_provenance": "rigctl.storage.provenance",
    "Session": "rigctl.storage.session",
    "SessionError": "rigctl.storage.session",
    "SessionWriter": "rigctl.storage.session",
    "open_session": "rigctl.storage.session",
}
if TYPE_CHECKING:
    # what static checkers see: the same names, typed (tests/test_public_api.py holds them equal to _EXPORTS)
    from rigctl.storage.encoded import (
        VARIANTS as VARIANTS,
        EncodedFile as EncodedFile,
        EncodedWriter as EncodedWriter,
        NotEncodedError as NotEncodedError,
        open_encoded as open_encoded,
    )
    from rigctl.storage.fabricslide import import_fabricslide as import_fabricslide
    from rigctl.storage.importers import ImportOptions as ImportOptions, import_recordings as import_recordings
    from rigctl.storage.model_file import (
        ModelFileError as ModelFileError,
        load_model as load_model,
        save_model as save_model,
    )
    from rigctl.storage.nwb import export_nwb as export_nwb
    from rigctl.storage.provenance import read_provenance as read_provenance
    from rigctl.storage.session import (
        Session as Session,
        SessionError as SessionError,
        SessionWriter as SessionWriter,
        open_session as open_session,
    )
else:
    __all__, __getattr__, __dir__ = lazy_exports(__name__, _EXPORTS)
