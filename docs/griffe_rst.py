"""Griffe extension: the docstrings' reStructuredText roles read as Markdown.

The docstrings are written for both ``help()`` and the site, in plain text with a few reST
habits: ``:func:`name```-style roles and a paragraph ending in ``::`` before an indented block.
Markdown renders the indented block as code already; this turns the ``::`` into ``:`` and each
role into a cross-reference to the object's entry in the API reference when that entry exists
(a public object with documentation, in a module that has a page), else into inline code.
``~a.b.c`` shows as ``c``; a relative name is looked up from the object, its class and its
module outwards.
"""

from __future__ import annotations

import re

import griffe

_ROLE = re.compile(r":(?:py:)?(?:func|class|mod|meth|attr|data|obj|exc|const):`(~?)([^`]+)`")
_LITERAL = re.compile(r"(\S)::[ \t]*$", re.MULTILINE)
_BARE = re.compile(r"^[ \t]*::[ \t]*$", re.MULTILINE)


def _documented(collection, path: str) -> str | None:
    """The canonical path of ``path``'s object when the API reference has an entry for it."""
    try:
        obj = collection[path]
        if obj.is_alias:
            obj = obj.final_target
    except Exception:  # not loaded (another package), not found, or an unresolvable alias
        return None
    parts = obj.path.split(".")
    if any(p.startswith("_") for p in parts) or not obj.has_docstrings:
        return None
    # A deprecated alias module has no page (docs/hooks.py), so nothing in it has an entry.
    cur = obj
    while cur is not None:
        if cur.is_module and cur.docstring is not None and cur.docstring.value.startswith("Deprecated"):
            return None
        cur = cur.parent
    return obj.path


def _scopes(obj: griffe.Object) -> list[str]:
    out, cur = [], obj
    while cur is not None:
        out.append(cur.path)
        cur = cur.parent
    return out


def rst_to_markdown(text: str, obj: griffe.Object | None = None) -> str:
    def role(m: re.Match) -> str:
        tilde, target = m.group(1), m.group(2).strip()
        shown = target.rsplit(".", 1)[-1] if tilde else target
        if obj is not None:
            collection = obj.modules_collection
            candidates = [target] + [f"{scope}.{target}" for scope in _scopes(obj)]
            for c in candidates:
                path = _documented(collection, c)
                if path is not None:
                    return f"[`{shown}`][{path}]"
        return f"`{shown}`"

    text = _ROLE.sub(role, text)
    text = _LITERAL.sub(r"\1:", text)
    return _BARE.sub("", text)


class RstRoles(griffe.Extension):
    def __init__(self) -> None:
        self._packages: list[griffe.Module] = []

    def on_package(self, *, pkg: griffe.Module, **kwargs) -> None:
        self._walk(pkg, set())

    def _walk(self, obj: griffe.Object, seen: set[int]) -> None:
        if id(obj) in seen:
            return
        seen.add(id(obj))
        if obj.docstring is not None:
            obj.docstring.value = rst_to_markdown(obj.docstring.value, obj)
        for member in obj.members.values():
            if not member.is_alias:
                self._walk(member, seen)
