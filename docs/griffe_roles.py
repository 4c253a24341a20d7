"""Griffe extension for the API reference: Sphinx roles in estim's docstrings become links.

estim's docstrings write cross-references the Sphinx way (``:func:`estim.simulate```,
``:class:`Tracks```), which Markdown would print verbatim. This turns each role into an
*optional* mkdocs-autorefs cross-reference: a link when the target is documented on the
site (``estim.X`` for a bare name ``X``), plain code otherwise, never a build warning.
Loaded by ``docs/mkdocs.yml`` (``extensions:`` of the python handler).
"""

from __future__ import annotations

import html
import re

import griffe

ROLE = re.compile(r":(?:func|class|meth|attr|mod|obj|data|exc):`~?([^`<>]+?)(?:\(\))?`")


def _link(match: re.Match) -> str:
    target = match.group(1).strip()
    identifier = target if target.startswith("estim") else f"estim.{target}"
    return (f'<autoref identifier="{html.escape(identifier)}" optional>'
            f"<code>{html.escape(target)}</code></autoref>")


class SphinxRoles(griffe.Extension):
    """Rewrite ``:role:`target``` in every docstring (see the module docstring)."""

    def on_object(self, *, obj: griffe.Object, **kwargs) -> None:
        if obj.docstring is not None and ":" in obj.docstring.value:
            obj.docstring.value = ROLE.sub(_link, obj.docstring.value)
