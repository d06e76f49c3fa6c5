"""A griffe extension for the API reference (mkdocs.yml): the docstrings cross-reference in Sphinx's roles
(``:class:`SensorLayout```, ``:func:`~rigctl.firmware.build```), which Markdown would show verbatim; they are
rendered as code (a leading ``~`` keeps only the last dotted part, as in Sphinx)."""

from __future__ import annotations

import re
from typing import Any

import griffe

_ROLE = re.compile(r":(?:py:)?(?:class|func|meth|mod|data|attr|exc|obj|const):`(~?)([^`]+)`")


def _as_code(m: re.Match) -> str:
    name = m.group(2)
    return f"`{name.rsplit('.', 1)[-1] if m.group(1) else name}`"


class SphinxRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = _ROLE.sub(_as_code, obj.docstring.value)
