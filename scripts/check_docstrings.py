"""Check the docstrings' form (CONTRIBUTING "Docstrings"): Google style, sections a reader can scan.

A public function or method (its name and its class's without a leading underscore) whose docstring
runs over more than one line, or that takes two or more parameters besides ``self``/``cls``, has:

- an ``Args:`` section naming every parameter (``*args``/``**kwargs`` by their names too), one per line;
- a ``Returns:`` (or ``Yields:``) section when it returns something (a return annotation other than
  ``None``/``NoReturn``), except a property;

and no docstring names an issue or a commit (``issue 14``, a 7-40 digit hex hash). Click commands are
left out: their docstring is the command's ``--help`` text, their parameters its documented options.

Usage: ``python scripts/check_docstrings.py [PATH ...]`` (default: the package); prints one line per
finding (``file:line: function: what``) and exits 1 if there is any.
"""
from __future__ import annotations

import ast
import re
import sys
from collections.abc import Iterator
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
DEFAULT_PATHS = ("ari_sfm", "factors", "pipelines")
SECTION = re.compile(r"^\s*(Args|Arguments|Returns|Yields|Raises|Attributes|Examples?|Notes?|See Also):\s*$", re.M)
HISTORY = re.compile(r"\b(issue|task) #?\d+\b|\bcommit [0-9a-f]{7,40}\b", re.I)
NO_RETURN = {"None", "NoReturn", "Never"}


def _python_files(paths: list[str]) -> Iterator[Path]:
    """Every .py file under ``paths`` once (the links ari_sfm/factors and ari_sfm/pipelines not followed)."""
    seen: set[Path] = set()
    for p in paths:
        path = (ROOT / p) if not Path(p).is_absolute() else Path(p)
        files = [path] if path.is_file() else sorted(path.rglob("*.py"))
        for f in files:
            if "_compiled" in f.parts or "__pycache__" in f.parts:
                continue
            real = f.resolve()
            if real not in seen:
                seen.add(real)
                yield real


def _is_click_command(fn: ast.FunctionDef) -> bool:
    """Decorated by click (``@click.command``, ``@group.command``, ``@click.option``...)."""
    for d in fn.decorator_list:
        text = ast.unparse(d)
        if "command" in text or "click." in text or "option(" in text or "_options" in text:
            return True
    return False


def _is_property(fn: ast.FunctionDef) -> bool:
    """A property or a cached property (its docstring says what the attribute is)."""
    return any(ast.unparse(d).split(".")[-1] in ("property", "cached_property", "setter") for d in fn.decorator_list)


def _parameters(fn: ast.FunctionDef) -> list[str]:
    """The parameters a caller passes, in order (not self/cls)."""
    a = fn.args
    names = [x.arg for x in [*a.posonlyargs, *a.args]]
    if names and names[0] in ("self", "cls"):
        names = names[1:]
    names += [x.arg for x in a.kwonlyargs]
    if a.vararg:
        names.append(a.vararg.arg)
    if a.kwarg:
        names.append(a.kwarg.arg)
    return names


def _section(doc: str, name: str) -> str | None:
    """The text of section ``name`` (up to the next section), or None."""
    matches = list(SECTION.finditer(doc))
    for i, m in enumerate(matches):
        if m.group(1) == name or (name == "Args" and m.group(1) == "Arguments"):
            end = matches[i + 1].start() if i + 1 < len(matches) else len(doc)
            return doc[m.end():end]
    return None


def _returns(fn: ast.FunctionDef) -> bool:
    """Whether the function's annotation says it returns a value."""
    if fn.returns is None:
        return any(isinstance(n, ast.Return) and n.value is not None for n in ast.walk(fn))
    return ast.unparse(fn.returns).strip("'\"") not in NO_RETURN


def check_function(fn: ast.FunctionDef, where: str) -> list[str]:
    """The findings for one function (empty when its docstring has the form)."""
    doc = ast.get_docstring(fn)
    if doc is None:
        return []
    out = []
    if HISTORY.search(doc):
        out.append(f"{where}: names an issue or a commit (history belongs in the design notes)")
    params = _parameters(fn)
    if "\n" not in doc.strip() and len(params) < 2:
        return out
    if params:
        args = _section(doc, "Args")
        if args is None:
            out.append(f"{where}: no Args section ({', '.join(params)})")
        else:
            missing = [p for p in params if not re.search(rf"^\s*\**{re.escape(p)}\b.*:", args, re.M)]
            if missing:
                out.append(f"{where}: Args does not name {', '.join(missing)}")
    if _returns(fn) and not _is_property(fn) and _section(doc, "Returns") is None and _section(doc, "Yields") is None:
        out.append(f"{where}: no Returns section")
    return out


def check_file(path: Path) -> list[str]:
    """The findings of one file."""
    tree = ast.parse(path.read_text(), filename=str(path))
    rel = path.relative_to(ROOT) if path.is_relative_to(ROOT) else path
    out: list[str] = []

    def visit(node: ast.AST, owner: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if child.name.startswith("_") or _is_click_command(child):  # type: ignore[arg-type]
                    continue
                out.extend(check_function(child, f"{rel}:{child.lineno}: {owner}{child.name}"))  # type: ignore[arg-type]
            elif isinstance(child, ast.ClassDef) and not child.name.startswith("_"):
                visit(child, f"{owner}{child.name}.")

    visit(tree, "")
    return out


def main(argv: list[str]) -> int:
    """Check the paths given (default: the package); print the findings; 1 if there are any."""
    findings = [f for path in _python_files(argv or list(DEFAULT_PATHS)) for f in check_file(path)]
    for f in findings:
        print(f)
    if findings:
        print(f"{len(findings)} docstring(s) not in the form (scripts/check_docstrings.py)", file=sys.stderr)
    return 1 if findings else 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
