"""The docstrings' form (CONTRIBUTING "Docstrings"): scripts/check_docstrings.py over the package finds nothing,
and the checker itself tells a docstring in the form from one that is not."""
from __future__ import annotations

import ast
import importlib.util
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def _checker():
    spec = importlib.util.spec_from_file_location("check_docstrings", ROOT / "scripts" / "check_docstrings.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _findings(source: str) -> list[str]:
    fn = ast.parse(source).body[0]
    assert isinstance(fn, ast.FunctionDef)
    return _checker().check_function(fn, "f")


def test_the_package_docstrings_are_in_the_form():
    checker = _checker()
    findings = [f for p in checker._python_files(list(checker.DEFAULT_PATHS)) for f in checker.check_file(p)]
    assert not findings, "\n".join(findings[:20]) + f"\n({len(findings)} in all; scripts/check_docstrings.py)"


def test_the_checker_tells_the_form_apart():
    good = '''def f(a: int, b: int) -> int:
    """Add.

    Args:
        a: One.
        b: Two.

    Returns:
        The sum.
    """
'''
    assert _findings(good) == []
    missing_arg = good.replace("        b: Two.\n", "")
    assert any("does not name b" in f for f in _findings(missing_arg))
    no_returns = good.replace("\n    Returns:\n        The sum.\n", "\n")
    assert any("no Returns" in f for f in _findings(no_returns))
    dense = 'def f(a: int, b: int) -> None:\n    """Add a to b and more,\n    in a paragraph."""\n'
    assert any("no Args" in f for f in _findings(dense))
    history = 'def f() -> None:\n    """Fixed in issue 14."""\n'
    assert any("issue or a commit" in f for f in _findings(history))
    one_line = 'def f(a: int) -> None:\n    """Use a."""\n'
    assert _findings(one_line) == []
