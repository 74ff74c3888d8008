"""``python -m benchmarks list`` and ``python -m benchmarks run NAME [options]`` (see :mod:`benchmarks`)."""

from __future__ import annotations

import ast
import runpy
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent


def benchmarks() -> dict[str, str]:
    """Each benchmark module's name and the first line of its docstring (read without importing it)."""
    out = {}
    for path in sorted(HERE.glob("*.py")):
        if path.name.startswith("_"):
            continue
        doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
        out[path.stem] = doc.strip().splitlines()[0] if doc.strip() else ""
    return out


def main(argv: list[str]) -> int:
    if argv[:1] == ["list"] and len(argv) == 1:
        names = benchmarks()
        width = max(map(len, names))
        for name, line in names.items():
            print(f"{name:<{width}}  {line}")
        return 0
    if argv[:1] == ["run"] and len(argv) >= 2:
        name = argv[1]
        if name not in benchmarks():
            print(f"benchmarks: no benchmark {name!r}; `python -m benchmarks list` names them", file=sys.stderr)
            return 2
        sys.argv = [f"benchmarks/{name}.py", *argv[2:]]
        runpy.run_module(f"benchmarks.{name}", run_name="__main__", alter_sys=True)
        return 0
    print(__doc__, file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
