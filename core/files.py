"""Reading a user's files: one reader, one number check.

Every file the project reads from a user or a run directory goes through
:func:`read_text` (or :func:`read_json`): its size is checked before a byte is read, so
a sparse 10 GB file costs nothing; it is decoded as UTF-8 with an optional byte-order
mark (what spreadsheets write as "CSV UTF-8"); and a failure is one line naming the file.
Every number read from such a file goes through :func:`number`: finite and within a
physically sensible range before any arithmetic, the file, line and column named.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import struct
from pathlib import Path

from chipstack.core.errors import InputError, brief, printable

__all__ = [
    "MAX_TEXT_BYTES",
    "MAX_GEOMETRY_BYTES",
    "check_size",
    "check_geometry_file",
    "file_sha256",
    "number",
    "read_json",
    "read_text",
]

MAX_TEXT_BYTES = 64 * 2**20  # a poses table of 100,000 chips is about 10 MB
MAX_GEOMETRY_BYTES = 64 * 2**20  # an ASCII STL of 200,000 triangles is about 50 MB
_STL_HEADER = 84  # 80 bytes of header, then the triangle count (uint32)
_STL_TRIANGLE = 50  # 12 floats and a 2-byte attribute


def check_size(path: str | Path, what: str, limit: int) -> int:
    """The size of the regular file ``path`` in bytes, refused above ``limit`` (before
    anything is read)."""
    shown = printable(path)
    try:
        status = os.stat(path)
    except OSError as exc:
        raise InputError(f"{shown}: cannot read the {what} ({exc.strerror or exc})") from None
    if not os.path.isfile(path):
        raise InputError(f"{shown}: is not a file; a {what} was expected")
    if status.st_size > limit:
        raise InputError(
            f"{shown}: the {what} holds {status.st_size:,} bytes; at most {limit:,} are read"
        )
    return status.st_size


def read_text(path: str | Path, what: str, limit: int = MAX_TEXT_BYTES) -> str:
    """The text of ``path``: size checked first, UTF-8 with or without a byte-order mark."""
    check_size(path, what, limit)
    try:
        with open(path, "rb") as f:
            data = f.read(limit + 1)  # a file growing while it is read stays bounded
    except OSError as exc:
        raise InputError(
            f"{printable(path)}: cannot read the {what} ({exc.strerror or exc})"
        ) from None
    if len(data) > limit:
        raise InputError(f"{printable(path)}: the {what} holds over {limit:,} bytes")
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(
            f"{printable(path)}: the {what} is not UTF-8 text (byte {exc.start})"
        ) from None


def read_json(path: str | Path, what: str, limit: int = MAX_TEXT_BYTES):
    """The parsed JSON file at ``path`` (size bounded; too deep a nesting refused), or one
    line naming it."""
    text = read_text(path, what, limit)
    try:
        return json.loads(text)
    except (json.JSONDecodeError, RecursionError) as exc:
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        raise InputError(f"{printable(path)}: unreadable {what} ({reason})") from None


def number(
    cell: object, where: str, column: str, low: float = -math.inf, high: float = math.inf
) -> float:
    """``cell`` (text or a number read from a file) as a float: finite, within
    [``low``, ``high``], else one line naming ``where`` (the file and line) and ``column``."""
    if isinstance(cell, bool):
        raise InputError(f"{where}: {column} {brief(cell)} is not a number")
    try:
        value = float(cell)
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"{where}: {column} {brief(cell)} is not a number") from None
    if not math.isfinite(value):
        raise InputError(f"{where}: {column} must be finite, got {brief(cell)}")
    if not low <= value <= high:
        raise InputError(f"{where}: {column} {value:g} is outside [{low:g}, {high:g}]")
    return value


def file_sha256(path: str | Path) -> str:
    """The SHA-256 of a file's bytes, read in blocks (a large file is never held whole)."""
    digest = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(2**20), b""):
            digest.update(block)
    return digest.hexdigest()


def check_geometry_file(path: str | Path, max_triangles: int) -> None:
    """Refuse, before it is read, a geometry file larger than ``MAX_GEOMETRY_BYTES`` or a
    binary STL whose declared triangle count exceeds ``max_triangles`` or disagrees with
    its size."""
    size = check_size(path, "geometry file", MAX_GEOMETRY_BYTES)
    if size == 0:
        raise InputError(f"{printable(path)}: the geometry file is empty")
    if Path(path).suffix.lower() != ".stl" or size < _STL_HEADER:
        return
    with open(path, "rb") as f:
        head = f.read(_STL_HEADER)
    (count,) = struct.unpack("<I", head[80:84])
    if size == _STL_HEADER + _STL_TRIANGLE * count:  # a binary STL
        if count > max_triangles:
            raise InputError(
                f"{printable(path)}: declares {count:,} triangles; at most {max_triangles:,} "
                "are accepted"
            )
        return
    if not head.lstrip().lower().startswith(b"solid"):  # binary, but not the size it says
        raise InputError(
            f"{printable(path)}: a binary STL declaring {count:,} triangles "
            f"({_STL_HEADER + _STL_TRIANGLE * count:,} bytes) holds {size:,} bytes"
        )
