"""A griffe extension for the documentation build: the code's docstrings cross-reference with reST roles
(``:class:`~rangemcl.raycast.RayCaster```), which the Markdown renderer would print as they are. Each role
becomes a code span of the name (its last part where the name starts with ``~``, as Sphinx shows it).
Loaded by mkdocstrings through ``mkdocs.yml``; the code is not changed."""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(
    r":(?:py:)?(?:class|func|meth|mod|attr|data|exc|obj|const|ref):`(~?)([^`<]+?)(?:\s*<[^>]*>)?`"
)


def _name(match: re.Match) -> str:
    short, name = match.group(1), match.group(2).strip()
    return f"`{name.rsplit('.', 1)[-1] if short else name}`"


class RstRoles(griffe.Extension):
    def on_instance(self, *, obj: griffe.Object, **kwargs: Any) -> None:
        if obj.docstring is not None:
            obj.docstring.value = ROLE.sub(_name, obj.docstring.value)
