"""The commands of ``pipeline``, one module each (``run``, ``scenarios``, ``sweep``,
``describe``, ``compare``, ``validate``, ``diagnose``, ``synth``), and what several of
them share.

Each module's ``main(args)`` takes the parsed command line. :mod:`chipstack.pipeline.cli`
builds the parser and imports a command's module only when that command runs, so that
``pipeline --help`` and a mistyped flag load none of the stages' libraries.
"""

from __future__ import annotations

import sys

from chipstack.core.errors import ChipstackError

__all__ = ["descriptor_names", "resumable_interrupt"]


def descriptor_names(text: str | None) -> list[str] | None:
    """``--descriptors``: the comma-separated names, or None when not given."""
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ChipstackError("--descriptors: give at least one descriptor name")
    return names


def resumable_interrupt(what: str, out) -> None:
    """Ctrl-C in a resumable command: say what is kept, exit 130."""
    sys.stderr.write(
        f"pipeline: interrupted; the {what} already written are kept in {out}: "
        "run the same command to resume\n"
    )
    raise SystemExit(130) from None
