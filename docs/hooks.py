"""MkDocs hooks for the dego site (see ``hooks:`` in mkdocs.yml; excluded from the site).

Docstrings in ``src/dego`` may name other objects with Sphinx roles (``:func:`splat```).
mkdocstrings' Google-style renderer keeps the role as literal text in front of the
inline code; this hook drops it, leaving the name as code.
"""

from __future__ import annotations

import re
from typing import Any

_ROLE = re.compile(r":(?:func|class|meth|attr|data|mod|obj|exc):(?=<code>)")


def on_page_content(html: str, **kwargs: Any) -> str:
    """Remove Sphinx role prefixes rendered before ``<code>`` in API pages."""
    return _ROLE.sub("", html)
