"""The service's layering: `workers` may import `services`, never the other way round. Every import statement of
every module under services/ is read with `ast` (function-level, lazy imports too), and `importlib.import_module`
/ `__import__` calls with a literal name are counted as imports."""

from __future__ import annotations

import ast
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def imported_names(tree: ast.AST) -> list[tuple[int, str]]:
    """(line, module) of every import in the tree, relative imports resolved against nothing (kept as '.x')."""
    out: list[tuple[int, str]] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = "." * node.level + (node.module or "")
            out.append((node.lineno, base))
            if node.level == 0 and node.module is None:
                out += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.Call) and node.args and isinstance(node.args[0], ast.Constant):
            func = node.func
            name = func.attr if isinstance(func, ast.Attribute) else func.id if isinstance(func, ast.Name) else ""
            if name in ("import_module", "__import__") and isinstance(node.args[0].value, str):
                out.append((node.lineno, node.args[0].value))
    return out


def test_imported_names_sees_lazy_and_dynamic_imports() -> None:
    code = ("def f():\n    from workers.celery_app import celery_app\n"
            "def g():\n    import workers.tasks as t\n"
            "def h():\n    importlib.import_module('workers')\n")  # fmt: skip
    assert [m for _, m in imported_names(ast.parse(code))] == ["workers.celery_app", "workers.tasks", "workers"]


def test_no_module_under_services_imports_workers() -> None:
    files = sorted((REPO / "services").rglob("*.py"))
    assert len(files) > 20
    bad = [f"{p.relative_to(REPO)}:{line}: {name}" for p in files
           for line, name in imported_names(ast.parse(p.read_text(), str(p)))
           if name == "workers" or name.startswith("workers.")]  # fmt: skip
    assert not bad, "services/ must not import workers (workers -> services only):\n" + "\n".join(bad)
