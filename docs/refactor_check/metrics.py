"""Size of a checkout's code: lines per package and the longest functions (AST, every def/method).

    python docs/refactor_check/metrics.py [ROOT]      (ROOT: a checkout; default: this one)
"""
import ast
import sys
from pathlib import Path

PACKAGES = ("pipeline", "render", "clean", "train", "evaluate", "tests")


def functions(root: Path):
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                    yield node.end_lineno - node.lineno + 1, f"{path.relative_to(root)}:{node.lineno} {node.name}"


if __name__ == "__main__":
    root = Path(sys.argv[1] if len(sys.argv) > 1 else Path(__file__).resolve().parents[2])
    for pkg in PACKAGES:
        files = sorted((root / pkg).rglob("*.py"))
        print(f"{pkg}: {len(files)} files, {sum(len(p.read_text().splitlines()) for p in files)} lines")
    print("longest functions:")
    for n, where in sorted(functions(root), reverse=True)[:12]:
        print(f"  {n:4d}  {where}")
