"""Figures of the code base: file and line counts, the largest files, public functions whose return type is a
dict, and uses of ``typing.Any`` (ari_sfm/, factors/, pipelines/).

    python scripts/house_stats.py [CHECKOUT]
"""
from __future__ import annotations

import ast
import re
import sys
from pathlib import Path

FOLDERS = ("ari_sfm", "factors", "pipelines")
DICT_RETURN = re.compile(r"^(dict|Dict|Mapping|MutableMapping)\b")


def main(root: Path) -> None:
    files = sorted({p.resolve() for d in FOLDERS for p in (root / d).rglob("*.py")})
    sizes = sorted(((len(p.read_text().splitlines()), p.relative_to(root.resolve()).as_posix()) for p in files),
                   reverse=True)
    dict_returns = anys = 0
    for path in files:
        source = path.read_text()
        for node in ast.walk(ast.parse(source)):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)) and not node.name.startswith("_") \
                    and node.returns is not None and DICT_RETURN.match(ast.unparse(node.returns)):
                dict_returns += 1
            elif isinstance(node, ast.Name) and node.id == "Any":
                anys += 1
            elif isinstance(node, ast.Attribute) and node.attr == "Any" and ast.unparse(node.value) == "typing":
                anys += 1
    print(f"files {len(files)}, lines {sum(s for s, _ in sizes)}")
    for lines, name in sizes[:8]:
        print(f"  {lines:5d} {name}")
    print(f"public functions returning a dict: {dict_returns}")
    print(f"uses of Any: {anys}")


if __name__ == "__main__":
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else Path(__file__).resolve().parents[1])
