"""Griffe extension for the API reference (mkdocs.yml): Sphinx roles in docstrings as cross-references.

The docstrings name other objects the Sphinx way, ``:func:`lbfgs```, ``:class:`~qtl.task.Task```,
``:meth:`Task.estimate_start```. mkdocstrings does not read reST roles; this extension rewrites each into an
optional cross-reference to the object it names, resolved in the docstring's own scope (its imports included):
a link where the object has a page in the reference, its name as code otherwise. ``~`` shows the last part only.
"""

from __future__ import annotations

import re
from typing import Any

import griffe

ROLE = re.compile(r":(?:py:)?(?:func|class|meth|attr|data|mod|obj|exc|const):`(?P<tilde>~?)(?P<target>[\w.]+)`")


def _resolve(obj: griffe.Object, target: str, collection: griffe.ModulesCollection) -> str | None:
    """The full path of ``target`` as seen from ``obj`` (absolute, or its first part resolved in obj's scope)."""
    first, _, rest = target.partition(".")
    candidates = [target]
    try:
        candidates.append(obj.resolve(first) + (f".{rest}" if rest else ""))
    except (griffe.NameResolutionError, ValueError, AttributeError):
        pass
    scope: griffe.Object | None = obj
    while scope is not None:  # a member a class inherits: where it is defined
        if scope.is_class:
            try:
                member = scope.all_members.get(first)  # type: ignore[union-attr]
            except (griffe.AliasResolutionError, griffe.CyclicAliasError, ValueError):
                member = None
            if member is not None:
                defined = member.target_path if member.is_alias else member.path
                candidates.append(defined + (f".{rest}" if rest else ""))
        scope = scope.parent
    for path in candidates:
        try:
            collection.get_member(path)
        except (KeyError, ValueError, AttributeError, griffe.AliasResolutionError, griffe.CyclicAliasError):
            continue
        return path
    return None


def _rewrite(obj: griffe.Object, text: str, collection: griffe.ModulesCollection) -> str:
    """``text`` with every role replaced by an optional autoref (a link if the target is documented)."""

    def replace(match: re.Match[str]) -> str:
        target = match["target"]
        shown = target.rsplit(".", 1)[-1] if match["tilde"] else target
        path = _resolve(obj, target, collection)
        if path is None:
            return f"`{shown}`"
        return f'<autoref identifier="{path}" optional><code>{shown}</code></autoref>'

    return ROLE.sub(replace, text)


class SphinxRoles(griffe.Extension):
    """Rewrite the Sphinx roles of every docstring of a loaded package (see the module docstring)."""

    def on_package(self, *, pkg: griffe.Module, loader: griffe.GriffeLoader, **kwargs: Any) -> None:
        """Walk the package's own objects (not aliases) once it is loaded, imports resolved."""
        stack: list[griffe.Object] = [pkg]
        while stack:
            obj = stack.pop()
            if obj.docstring is not None and ":" in obj.docstring.value:
                obj.docstring.value = _rewrite(obj, obj.docstring.value, loader.modules_collection)
            stack.extend(member for member in obj.members.values() if not member.is_alias)
