"""No function of the product is over 100 lines (its whole span: decorators, signature, docstring
and body), except the compiled kernels (Numba ``@njit`` / ``@cuda.jit``), whose loop body must stay
one function to compile well."""

from __future__ import annotations

import ast

from helpers import REPO

PACKAGES = ("sim", "calibration", "pipeline", "data_schemas")
MAX_LINES = 100
KERNEL_DECORATORS = {"njit", "jit"}  # numba.njit, numba.jit, cuda.jit, with or without arguments


def _is_kernel(fn: ast.FunctionDef | ast.AsyncFunctionDef) -> bool:
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in KERNEL_DECORATORS:
            return True
    return False


def long_functions() -> list[str]:
    found = []
    for pkg in PACKAGES:
        for path in sorted((REPO / pkg).rglob("*.py")):
            rel = path.relative_to(REPO).as_posix()
            for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"), rel)):
                if not isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) or _is_kernel(node):
                    continue
                start = min([node.lineno] + [d.lineno for d in node.decorator_list])
                lines = node.end_lineno - start + 1
                if lines > MAX_LINES:
                    found.append(f"{rel}:{start} {node.name}: {lines} lines")
    return found


def test_no_function_over_100_lines():
    assert long_functions() == [], "split these into parts named for what they do"


def test_the_check_sees_a_long_function_and_skips_a_kernel():
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    plain = ast.parse(f"def f():\n{body}\n").body[0]
    kernel = ast.parse(f"@njit(cache=True)\ndef f():\n{body}\n").body[0]
    assert plain.end_lineno - plain.lineno + 1 > MAX_LINES
    assert not _is_kernel(plain) and _is_kernel(kernel)
