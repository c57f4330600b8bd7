"""MkDocs hooks: the docstrings' Sphinx roles (``:meth:`Printer.events```) read as the code
they name in the API reference, as they do in an editor's hover."""

from __future__ import annotations

import re
from typing import Any

# mkdocstrings renders ":meth:`a.B.c`" as ":meth:<code>a.B.c</code>"; a "~" shows the
# last part alone, as Sphinx does.
ROLE = re.compile(r":(?:meth|class|attr|func|data|mod|exc|obj):(<code>)(?:~[\w.]*\.)?")


def on_page_content(html: str, **_: Any) -> str:
    return ROLE.sub(r"\1", html)
