"""Griffe extension: the docstrings' reStructuredText roles read as Markdown.

The docstrings are written for both ``help()`` and the site, in plain text with a few
reST habits: ``:func:`name```-style roles and a paragraph ending in ``::`` before an
indented block.  Markdown renders the indented block as code already; this turns each role
into inline code (``~a.b.c`` shows as ``c``) and the ``::`` into ``:``.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):`(~?)([^`]+)`")
_LITERAL = re.compile(r"(\S)::[ \t]*$", re.MULTILINE)
_BARE = re.compile(r"^[ \t]*::[ \t]*$", re.MULTILINE)


def rst_to_markdown(text: str) -> str:
    text = _ROLE.sub(lambda m: f"`{m.group(2).rsplit('.', 1)[-1] if m.group(1) else m.group(2)}`", text)
    text = _LITERAL.sub(r"\1:", text)
    return _BARE.sub("", text)


class RstRoles(griffe.Extension):
    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        self._walk(pkg, set())

    def _walk(self, obj: griffe.Object, seen: set[int]) -> None:
        if id(obj) in seen:
            return
        seen.add(id(obj))
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value)
        for member in obj.members.values():
            if not member.is_alias:
                self._walk(member, seen)
