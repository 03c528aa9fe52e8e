"""Counts of tests in the docs, taken from pytest's collection (issue 74): none is written
by hand. A count in a page is the number between the markers

    <!-- count:test_bad_input.py -->162<!-- /count -->
    <!-- count:test_bad_input.py::test_bad_flag+test_bad_synth_flag -->29<!-- /count -->

the collected cases (parametrised ones each) of a test module under ``tests/``, or of the
named test functions of it, joined by ``+``. ``python tests/collected.py`` (run by
``make docs``) writes the counts; ``tests/test_test_quality.py`` fails when a page's
count is not the collection's.
"""

from __future__ import annotations

import logging
import re
import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
MARK = re.compile(r"<!-- count:(?P<what>[\w.]+(?:::[\w+]+)?) -->(?P<n>[0-9,]*)<!-- /count -->")


def collect(modules: list[str]) -> Counter:
    """``(module, function)`` -> collected cases, for test modules named as in tests/."""
    if not modules:
        return Counter()
    done = subprocess.run(
        [sys.executable, "-m", "pytest", "--collect-only", "-q", "-p", "no:cacheprovider"]
        + [f"tests/{m}" for m in sorted(set(modules))],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=600,
    )
    if done.returncode != 0:
        raise RuntimeError(f"pytest --collect-only failed:\n{done.stdout[-2000:]}{done.stderr}")
    counts = Counter()
    for line in done.stdout.splitlines():
        if line.startswith("tests/") and "::" in line:
            module, function = line.removeprefix("tests/").split("::", 1)
            counts[module, function.split("[", 1)[0]] += 1
    return counts


def count(what: str, counts: Counter) -> int:
    module, _, functions = what.partition("::")
    if not functions:
        return sum(n for (m, _), n in counts.items() if m == module)
    found = 0
    for function in functions.split("+"):
        if (module, function) not in counts:
            raise KeyError(f"count:{what}: {module} collects no {function}")
        found += counts[module, function]
    return found


def _pages(folder: Path) -> dict[Path, str]:
    return {page: page.read_text() for page in sorted(folder.glob("*.md"))}


def _counts(pages: dict[Path, str]) -> Counter:
    wanted = [m["what"].partition("::")[0] for text in pages.values() for m in MARK.finditer(text)]
    return collect(wanted)


def _rendered(text: str, counts: Counter) -> str:
    return MARK.sub(
        lambda m: f"<!-- count:{m['what']} -->{count(m['what'], counts):,}<!-- /count -->", text
    )


def stale(folder: Path = DOCS, counts: Counter | None = None) -> list[str]:
    """``page: what written, collected`` for every count that is not the collection's
    (``counts``: as :func:`collect` gives them; collected when not given)."""
    pages = _pages(folder)
    counts = _counts(pages) if counts is None else counts
    found = []
    for page, text in pages.items():
        for m in MARK.finditer(text):
            n = f"{count(m['what'], counts):,}"
            if m["n"] != n:
                found.append(f"{page.name}: {m['what']} says {m['n'] or 'nothing'}, {n} collected")
    return found


def refresh(folder: Path = DOCS, counts: Counter | None = None) -> list[str]:
    """Write the collection's counts into every page; returns the pages changed."""
    pages = _pages(folder)
    counts = _counts(pages) if counts is None else counts
    changed = []
    for page, text in pages.items():
        new = _rendered(text, counts)
        if new != text:
            page.write_text(new)
            changed.append(page.name)
    return changed


if __name__ == "__main__":
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    for name in refresh():
        logging.getLogger("collected").info("counts refreshed in docs/%s", name)
