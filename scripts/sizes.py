"""Modules over 450 lines and functions over 80 lines under a folder (default src/), for docs/architecture.md.

A function's size is ``end_lineno - lineno + 1`` (its nested functions included). Usage: python scripts/sizes.py [DIR]
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

MAX_MODULE, MAX_FUNCTION = 450, 80


def oversized(root: Path) -> list[str]:
    """One line per module or function over the limits, in path order."""
    out = []
    for p in sorted(root.rglob("*.py")):
        text = p.read_text(encoding="utf-8")
        if (n := len(text.splitlines())) > MAX_MODULE:
            out.append(f"module {p.relative_to(root)}: {n} lines")
        for node in ast.walk(ast.parse(text, str(p))):
            is_def = isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
            if is_def and (n := node.end_lineno - node.lineno + 1) > MAX_FUNCTION:
                out.append(f"function {p.relative_to(root)}:{node.name}: {n} lines")
    return out


if __name__ == "__main__":
    print("\n".join(oversized(Path(sys.argv[1] if len(sys.argv) > 1 else "src"))))
