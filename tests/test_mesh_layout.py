"""Layout rules of the code base (issue 11): small modules, short stage-1 functions."""

from __future__ import annotations

import ast
from pathlib import Path

import pavemap

SRC = Path(pavemap.__file__).parent
MAX_MODULE_LINES = 450
MAX_FUNCTION_LINES = 80


def test_no_module_over_450_lines():
    long = {str(f.relative_to(SRC)): n for f in sorted(SRC.rglob("*.py"))
            if (n := len(f.read_text(encoding="utf-8").splitlines())) > MAX_MODULE_LINES}
    assert not long, f"modules over {MAX_MODULE_LINES} lines: {long}"


def test_no_mesh_function_over_80_lines():
    long = {}
    for f in sorted((SRC / "mesh").rglob("*.py")):
        for node in ast.walk(ast.parse(f.read_text(encoding="utf-8"))):
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
                n = node.end_lineno - node.lineno + 1
                if n > MAX_FUNCTION_LINES:
                    long[f"{f.relative_to(SRC)}:{node.name}"] = n
    assert not long, f"functions over {MAX_FUNCTION_LINES} lines: {long}"
