"""pxr's own diagnostics turned into one line a user can act on.

pxr reports a missing sublayer, a file that is not USD or a broken reference as C++
text on the process's stderr (``Warning: in _ReportErrors at line 3326 of
.../stage.cpp -- Could not load sublayer @x.usda@ ...``) and carries on, so a stage
would be simulated without the part that did not load. ``captured_stderr`` takes
that text while a stage opens; ``pxr_reason`` keeps its readable part.
"""

from __future__ import annotations

import os
import re
import sys
import tempfile
from contextlib import contextmanager


@contextmanager
def captured_stderr(lines: list):
    """Redirect file descriptor 2 (where pxr's C++ code writes) into ``lines`` for
    the block; the lines that look like diagnostics are appended when it ends."""
    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):       # no real stderr: nothing to capture
        yield
        return
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)
            tmp.seek(0)
            text = tmp.read().decode(errors="replace")
            lines.extend(ln.strip() for ln in text.splitlines()
                         if re.match(r"\s*(Warning|Error|Coding Error|Fatal)", ln)
                         or " -- " in ln)


def pxr_reason(lines) -> str:
    """The readable part of pxr's first diagnostic: the text after its source
    location (``... -- TEXT``) or inside its quotes (``... : 'TEXT'``), without the
    trailing note in parentheses."""
    for ln in lines:
        ln = ln.strip()
        if not ln:
            continue
        if " -- " in ln:
            text = ln.split(" -- ", 1)[1]
        elif re.search(r": '(.*)'\s*$", ln):
            text = re.search(r": '(.*)'\s*$", ln).group(1)
        else:
            text = ln
        text = re.sub(r"\s*\((?:Recomposing|instantiating) stage[^)]*\)\s*$", "", text)
        return text.strip()
    return ""
