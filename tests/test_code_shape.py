"""The shape of the code: no function in ``src/n2f2`` longer than ``MAX_LINES``, except compiled
kernels that say at their top why they are one function (a numba kernel cannot call a Python
helper and each call out of it costs), checked with ``ast`` and tried first on a fake module."""

from __future__ import annotations

import ast
from pathlib import Path

import n2f2

MAX_LINES = 150
PACKAGE_ROOT = Path(n2f2.__file__).parent
KERNEL_DECORATORS = ("njit", "jit", "vectorize", "guvectorize", "stencil")
REASON = "one function because"  # the phrase a long kernel's docstring gives its reason with


def _decorator_name(node: ast.expr) -> str:
    if isinstance(node, ast.Call):
        node = node.func
    if isinstance(node, ast.Attribute):
        return node.attr
    return node.id if isinstance(node, ast.Name) else ""


def long_functions(source: str, max_lines: int = MAX_LINES) -> list[tuple[str, int, str]]:
    """``(name, lines, why it is refused)`` of every function longer than ``max_lines`` that is
    not a compiled kernel giving its reason (``REASON``) in its docstring."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            continue
        lines = node.end_lineno - node.lineno + 1  # type: ignore[operator]
        if lines <= max_lines:
            continue
        kernel = any(_decorator_name(d) in KERNEL_DECORATORS for d in node.decorator_list)
        doc = (ast.get_docstring(node) or "").lower()
        if not kernel:
            found.append((node.name, lines, "not a compiled kernel"))
        elif REASON not in " ".join(doc.split()):
            found.append((node.name, lines, f"a kernel whose docstring does not say why ({REASON!r})"))
    return found


def _function(name: str, body_lines: int, decorator: str = "", doc: str = "") -> str:
    head = f"@{decorator}\n" if decorator else ""
    text = f'    """{doc}"""\n' if doc else ""
    return head + f"def {name}():\n" + text + "    x = 1\n" * body_lines


def test_checker_on_a_fake_module():
    # Line counts by hand: def line + body; a docstring adds one line.
    source = "\n".join([
        _function("short", 149),  # 150 lines: allowed
        _function("long", 150),  # 151 lines: refused
        _function("kernel_without_reason", 160, "numba.njit(cache=True)"),
        _function("kernel_with_reason", 160, "njit", "One function because the kernel\n    cannot call helpers."),
        "class A:\n" + "\n".join("    " + line for line in _function("method", 151).splitlines()),
    ])
    found = long_functions(source)
    assert [(n, k) for n, k, _ in found] == [("long", 151), ("kernel_without_reason", 161), ("method", 152)]
    assert "not a compiled kernel" in found[0][2] and "does not say why" in found[1][2]


def test_no_function_in_the_package_is_longer_than_the_limit():
    problems = [
        f"{path.relative_to(PACKAGE_ROOT)}: {name} ({lines} lines): {why}"
        for path in sorted(PACKAGE_ROOT.rglob("*.py"))
        for name, lines, why in long_functions(path.read_text())
    ]
    assert problems == []
