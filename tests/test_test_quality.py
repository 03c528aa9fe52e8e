"""The tests themselves (issue 74): a test that cannot fail is a defect. An AST walk of
every module under ``tests/`` finds

* a test function that asserts nothing. A test asserts when its body (nested blocks and
  functions included) holds an ``assert`` statement, a ``pytest.raises`` or
  ``pytest.warns``, a call of a function named ``assert_*`` (numpy.testing's, or the
  tests' own such as ``assert_refused``), or a call of a helper defined in the test tree
  that asserts by this same rule (``run_scenario``, which asserts the run succeeded;
  followed through helpers calling helpers). A product function such as ``check_mesh``
  is not an assertion: only what the test tree defines counts;
* assertions that cannot fail, where the assert's truth rests on them (the expression,
  its and/or/not operands, what all() or any() takes; not a mask inside an index):
  ``x >= 0`` or ``0 <= x``, as a quantity such as a count, a length or a spread is never
  negative (a difference, ``a - b`` or ``np.diff(x)``, is signed and exempt);
  ``0 <= x <= 1`` or ``0 < x <= 1``, which every p-value or share passes;
  ``f(...) is not None`` where ``f`` reads or loads (``read``, ``load``, ``open``...),
  as a reader returns a value or raises; ``.get(key, default)`` anywhere in an assert,
  where a missing key passes as the default;
* ``pytest.raises(Exception)`` or ``pytest.raises(BaseException)``: the error's own type
  must be named (and its message matched);
* an ``except`` clause whose body only passes or continues: cases dropped in silence;
* a pytest mark on a function pytest does not collect (a helper), which marks nothing.

A signed quantity compared with 0 is a real assertion: name it in the assert's line
with the comment ``# signed`` (two in the tree: a fitted vertex and a separation).
Each rule has its broken case. The module also checks that the counts of tests written
in docs/ are those pytest collects (``tests/collected.py``).
"""

from __future__ import annotations

import ast
import io
import re
import tokenize
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent


def _is_test(node: ast.AST) -> bool:
    return isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.startswith("test")


def _called_name(call: ast.Call) -> str | None:
    func = call.func
    if isinstance(func, ast.Name):
        return func.id
    if isinstance(func, ast.Attribute):
        return func.attr
    return None


def _is_pytest(call: ast.Call, *names: str) -> bool:
    func = call.func
    return (
        isinstance(func, ast.Attribute)
        and func.attr in names
        and isinstance(func.value, ast.Name)
        and func.value.id == "pytest"
    )


def _asserts_directly(function: ast.AST) -> bool:
    for node in ast.walk(function):
        if isinstance(node, ast.Assert):
            return True
        if isinstance(node, ast.Call):
            if _is_pytest(node, "raises", "warns"):
                return True
            name = _called_name(node)
            if name is not None and name.startswith("assert_"):
                return True
    return False


def _calls(function: ast.AST) -> set[str]:
    return {
        name
        for node in ast.walk(function)
        if isinstance(node, ast.Call) and (name := _called_name(node)) is not None
    }


def asserting_helpers(trees: list[ast.Module]) -> set[str]:
    """Names of the functions defined in ``trees`` (outside test functions) that assert,
    directly or through another such helper: the closure of the rule above."""
    helpers: dict[str, list[ast.AST]] = {}
    for tree in trees:
        for node in ast.walk(tree):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and not _is_test(node):
                helpers.setdefault(node.name, []).append(node)
    asserting = {n for n, defs in helpers.items() if any(_asserts_directly(d) for d in defs)}
    while True:
        more = {
            n
            for n, defs in helpers.items()
            if n not in asserting and any(_calls(d) & asserting for d in defs)
        }
        if not more:
            return asserting
        asserting |= more


def _is_zero(node: ast.AST) -> bool:
    return isinstance(node, ast.Constant) and type(node.value) in (int, float) and node.value == 0


def _truths(expr: ast.expr):
    """The parts of an assert's expression whose truth it asserts: the expression, the
    operands of and/or/not, and what all()/any() (also numpy's and ``(...).all()``) take;
    not a comparison inside an index (``chips[chips >= 0]``, a mask)."""
    yield expr
    if isinstance(expr, ast.BoolOp):
        for value in expr.values:
            yield from _truths(value)
    elif isinstance(expr, ast.UnaryOp) and isinstance(expr.op, ast.Not):
        yield from _truths(expr.operand)
    elif isinstance(expr, ast.Call) and _called_name(expr) in ("all", "any"):
        inner = expr.args[0] if expr.args else getattr(expr.func, "value", None)
        if isinstance(inner, ast.GeneratorExp | ast.ListComp):
            inner = inner.elt
        if inner is not None:
            yield from _truths(inner)


def _difference(node: ast.AST) -> bool:
    """``a - b`` or ``np.diff(x)``: a signed quantity, its comparison with 0 a real one."""
    return (isinstance(node, ast.BinOp) and isinstance(node.op, ast.Sub)) or (
        isinstance(node, ast.Call) and _called_name(node) == "diff"
    )


READERS = re.compile(r"(^|_)(read|reads|load|loads|imread|open)(_|$)")


def _vacuous(test: ast.expr) -> list[str]:
    """What in an assert's expression cannot fail."""
    found = []
    for node in _truths(test):
        if not isinstance(node, ast.Compare):
            continue
        operands = [node.left, *node.comparators]
        if (
            len(node.ops) == 2
            and _is_zero(node.left)
            and isinstance(node.comparators[1], ast.Constant)
            and node.comparators[1].value == 1
            and isinstance(node.ops[0], ast.Lt | ast.LtE)
            and isinstance(node.ops[1], ast.LtE)
        ):
            found.append(f"'{ast.unparse(node)}': a p-value or a share, always in [0, 1]")
            continue
        for op, left, right in zip(node.ops, operands[:-1], operands[1:], strict=True):
            if isinstance(op, ast.GtE) and _is_zero(right) and not _difference(left):
                found.append(f"'{ast.unparse(left)} >= 0': a quantity compared with 0")
            if isinstance(op, ast.LtE) and _is_zero(left) and not _difference(right):
                found.append(f"'0 <= {ast.unparse(right)}': a quantity compared with 0")
            if (
                isinstance(op, ast.IsNot)
                and isinstance(left, ast.Call)
                and READERS.search(_called_name(left) or "")
                and isinstance(right, ast.Constant)
                and right.value is None
            ):
                found.append(f"'{ast.unparse(left)} is not None': a reader returns or raises")
    for node in ast.walk(test):
        if (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "get"
            and len(node.args) + len(node.keywords) >= 2
        ):
            found.append(f"'{ast.unparse(node)}': a missing key passes as the default")
    return found


def _signed_lines(source: str) -> set[int]:
    return {
        token.start[0]
        for token in tokenize.generate_tokens(io.StringIO(source).readline)
        if token.type == tokenize.COMMENT and token.string.startswith("# signed")
    }


def _broad(call: ast.Call) -> bool:
    return (
        _is_pytest(call, "raises")
        and bool(call.args)
        and isinstance(call.args[0], ast.Name)
        and call.args[0].id in ("Exception", "BaseException")
    )


def _silent(handler: ast.ExceptHandler) -> bool:
    return all(isinstance(s, ast.Pass | ast.Continue) for s in handler.body)


def _marks(function: ast.AST) -> list[str]:
    return [
        ast.unparse(d)
        for d in function.decorator_list
        if ast.unparse(d).startswith(("pytest.mark.", "needs("))
    ]


def problems(source: str, where: str, helpers: set[str]) -> list[str]:
    """``where:line: what`` for every rule of this module ``source`` breaks; ``helpers``:
    the test tree's asserting helpers (:func:`asserting_helpers`)."""
    tree = ast.parse(source)
    signed = _signed_lines(source)
    found = []
    for node in ast.walk(tree):
        at = f"{where}:{getattr(node, 'lineno', 0)}"
        if _is_test(node):
            if not (_asserts_directly(node) or _calls(node) & helpers):
                found.append(f"{at}: {node.name} asserts nothing")
        elif isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and _marks(node):
            found.append(f"{at}: {', '.join(_marks(node))} on {node.name}, not a test")
        if isinstance(node, ast.Assert) and node.lineno not in signed:
            found += [f"{at}: {what}" for what in _vacuous(node.test)]
        if isinstance(node, ast.Call) and _broad(node):
            found.append(f"{at}: {ast.unparse(node)}: name the error's own type")
        if isinstance(node, ast.ExceptHandler) and _silent(node):
            caught = ast.unparse(node.type) if node.type else "everything"
            found.append(f"{at}: except {caught}: drops what it catches in silence")
    return found


def _modules() -> dict[str, str]:
    return {
        path.relative_to(TESTS.parent).as_posix(): path.read_text()
        for path in sorted(TESTS.rglob("*.py"))
        if path.name.startswith(("test_", "conftest")) or path.parent == TESTS
    }


def test_every_test_asserts_something_that_can_fail():
    modules = _modules()
    helpers = asserting_helpers([ast.parse(s) for s in modules.values()])
    assert "run_scenario" in helpers and "assert_refused" in helpers  # the rule's own basis
    found = [p for where, source in modules.items() for p in problems(source, where, helpers)]
    assert found == [], "\n".join(found)


BROKEN = """
import pytest

def helper_that_asserts(x):
    assert x == 1

def helper_calling_it(x):
    helper_that_asserts(x)

@pytest.mark.slow
def _marked_helper():
    return 1

def test_nothing():
    value = compute()
    print(value)

def test_through_a_product_check():
    check_mesh(mesh)

def test_through_helpers():
    helper_calling_it(1)

def test_numpy():
    np.testing.assert_allclose(1.0, 1.0)

def test_vacuous():
    summary = load()
    assert summary["cv"] >= 0
    assert 0 <= summary["p"] <= 1
    assert 0 < summary["calibrated_p"] <= 1
    assert pyvista.read(path) is not None
    assert summary.get("valid", True)
    assert summary["gap"] >= 0  # signed: a gap may be negative

def test_broad():
    with pytest.raises(Exception, match="x"):
        run()
    for value in values:
        try:
            check(value)
        except TypeError:
            continue
"""


def test_the_check_flags_each_broken_form():
    helpers = asserting_helpers([ast.parse(BROKEN)])
    assert helpers == {"helper_that_asserts", "helper_calling_it"}
    found = problems(BROKEN, "broken.py", helpers)
    expected = [
        "broken.py:11: pytest.mark.slow on _marked_helper, not a test",
        "broken.py:14: test_nothing asserts nothing",
        "broken.py:18: test_through_a_product_check asserts nothing",
        "broken.py:29: 'summary['cv'] >= 0': a quantity compared with 0",
        "broken.py:30: '0 <= summary['p'] <= 1': a p-value or a share, always in [0, 1]",
        "broken.py:31: '0 < summary['calibrated_p'] <= 1': a p-value or a share, always in [0, 1]",
        "broken.py:32: 'pyvista.read(path) is not None': a reader returns or raises",
        "broken.py:33: 'summary.get('valid', True)': a missing key passes as the default",
        "broken.py:37: pytest.raises(Exception, match='x'): name the error's own type",
        "broken.py:42: except TypeError: drops what it catches in silence",
    ]
    assert sorted(found, key=lambda p: int(p.split(":")[1])) == expected


FIXED = [
    "def test_a():\n    assert summary['cv'] == pytest.approx(cv)\n",
    "def test_a():\n    assert summary['gap'] >= 0  # signed: an overlap is negative\n",
    "def test_a():\n    with pytest.raises(InputError, match='^x: '):\n        run()\n",
    "def test_a():\n    assert summary['valid'] is True\n",
    "def test_a():\n    assert p == pytest.approx(reaching / 20) and p >= alpha\n",
]


@pytest.mark.parametrize("fixed", FIXED)
def test_the_check_passes_the_fixed_forms(fixed):
    assert problems(fixed, "fixed.py", set()) == []


def test_the_docs_counts_are_the_collections():
    """Every count of tests in docs/ is pytest's (tests/collected.py; ``make docs``)."""
    from collected import stale

    assert stale() == [], "counts of tests in docs/ are stale: run `make docs`"


def test_the_counts_check_reports_a_stale_count_and_refreshes_it(tmp_path):
    from collections import Counter

    from collected import refresh, stale

    counts = Counter({("test_a.py", "test_flag"): 29, ("test_a.py", "test_one"): 1})
    page = tmp_path / "page.md"
    page.write_text(
        "the catalogue (<!-- count:test_a.py::test_flag -->3<!-- /count --> flags of "
        "<!-- count:test_a.py -->1,030<!-- /count --> tests)\n"
    )
    assert stale(tmp_path, counts) == [
        "page.md: test_a.py::test_flag says 3, 29 collected",
        "page.md: test_a.py says 1,030, 30 collected",
    ]
    assert refresh(tmp_path, counts) == ["page.md"] and stale(tmp_path, counts) == []
    assert "-->29<!--" in page.read_text() and "-->30<!--" in page.read_text()
    page.write_text("<!-- count:test_a.py::test_no_such_test -->1<!-- /count -->\n")
    with pytest.raises(KeyError, match="test_a.py collects no test_no_such_test"):
        stale(tmp_path, counts)
