"""Structure of the pipeline package: imports at module level only, so a cycle cannot hide in a function."""

from __future__ import annotations

import ast
from pathlib import Path

PIPELINE = Path(__file__).resolve().parents[2] / "pipeline"


def test_no_imports_inside_functions() -> None:
    found = []
    for path in sorted(PIPELINE.rglob("*.py")):
        for fn in ast.walk(ast.parse(path.read_text())):
            if isinstance(fn, ast.FunctionDef | ast.AsyncFunctionDef):
                found += [f"{path.name}:{node.lineno} in {fn.name}" for node in ast.walk(fn)
                          if isinstance(node, ast.Import | ast.ImportFrom)]
    assert not found, found


def test_parameters_live_in_the_parameter_tree() -> None:
    """Every tunable is a field of :mod:`pipeline.params`, documented right below it."""
    tree = ast.parse((PIPELINE / "params.py").read_text())
    undocumented = []
    for cls in (n for n in tree.body if isinstance(n, ast.ClassDef) and n.name.endswith("Params")):
        body = cls.body
        for i, stmt in enumerate(body):
            if isinstance(stmt, ast.AnnAssign) and cls.name != "PipelineParams":
                doc = body[i + 1] if i + 1 < len(body) else None
                if not (isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant)):
                    undocumented.append(f"{cls.name}.{stmt.target.id}")  # type: ignore[union-attr]
    assert not undocumented, undocumented
