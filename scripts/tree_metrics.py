"""Size and shape of the package tree, for before/after comparisons of a restructure.

    python scripts/tree_metrics.py [--root src/taptr] [--json]

Prints: files, median and largest file (lines), median and longest function, functions over
80 lines, public names exported by ``taptr``, file names used more than once, and the import
floors: packages ordered so that each imports only packages on lower floors (a package on
the same floor as another it imports means a cycle).
"""

from __future__ import annotations

import argparse
import ast
import importlib
import json
import statistics
import sys
from collections import Counter
from pathlib import Path

LONG_FUNCTION = 80


def _functions(tree: ast.AST) -> list[tuple[str, int]]:
    spans = []
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef):
            assert node.end_lineno is not None
            spans.append((node.name, node.end_lineno - node.lineno + 1))
    return spans


def _room(module: str, packages: set[str]) -> str:
    """Where a module lives: ``taptr.model.ops.gather`` → ``model/``, ``taptr.geometry`` → as is."""
    parts = module.split(".")
    if len(parts) == 1:
        return "__init__"
    return f"{parts[1]}/" if parts[1] in packages else parts[1]


def _imports(tree: ast.AST) -> set[str]:
    found = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            if node.module.startswith("taptr"):
                found.add(node.module)
                found.update(f"{node.module}.{alias.name}" for alias in node.names)
        elif isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.startswith("taptr"))
    return found


def floors(edges: dict[str, set[str]], rooms: set[str], strict: bool = False) -> list[list[str]]:
    """Rooms top-down: the lowest floor imports nothing else; a room sits above all it imports.

    A cycle puts the rooms left on one floor, or raises ValueError naming them if ``strict``.
    """
    floor: dict[str, int] = {}
    remaining = set(rooms)
    level = 0
    while remaining:
        ready = {r for r in remaining if edges[r] - {r} <= set(floor)}
        if not ready:  # a cycle: put the rest on one floor
            if strict:
                raise ValueError(f"an import cycle among {sorted(remaining)}")
            ready = set(remaining)
        for room in ready:
            floor[room] = level
        remaining -= ready
        level += 1
    out: list[list[str]] = [[] for _ in range(level)]
    for room, index in floor.items():
        out[index].append(room)
    return [sorted(f) for f in out][::-1]


def _module_name(path: Path, root: Path) -> str:
    relative = path.relative_to(root.parent).with_suffix("")
    return ".".join(p for p in relative.parts if p != "__init__")


def room_graph(
    root: Path,
) -> tuple[set[str], dict[str, set[str]], dict[tuple[str, str], str]]:
    """The rooms under ``root``, which rooms each imports, and one import behind each edge."""
    files = sorted(root.rglob("*.py"))
    packages = {p.relative_to(root).parts[0] for p in files if p.parent != root}
    rooms = {_room(_module_name(p, root), packages) for p in files}
    edges: dict[str, set[str]] = {room: set() for room in rooms}
    witnesses: dict[tuple[str, str], str] = {}
    for path in files:
        module = _module_name(path, root)
        room = _room(module, packages)
        for imported in sorted(_imports(ast.parse(path.read_text()))):
            target = _room(imported, packages)
            if target in rooms and target != room:
                edges[room].add(target)
                witnesses.setdefault((room, target), f"{module} imports {imported}")
    return rooms, edges, witnesses


def measure(root: Path) -> dict[str, object]:
    """Metrics of every ``.py`` file under ``root`` (the package folder)."""
    files = sorted(root.rglob("*.py"))
    lines, spans = {}, []
    for path in files:
        text = path.read_text()
        lines[str(path.relative_to(root))] = len(text.splitlines())
        tree = ast.parse(text)
        spans += [(f"{path.relative_to(root)}:{name}", n) for name, n in _functions(tree)]
    rooms, edges, _ = room_graph(root)
    sys.path.insert(0, str(root.parent))
    public = importlib.import_module(root.name).__all__
    names = Counter(p.name for p in files if p.name != "__init__.py")
    longest = max(spans, key=lambda s: s[1])
    biggest = max(lines.items(), key=lambda kv: kv[1])
    return {
        "files": len(files),
        "lines": sum(lines.values()),
        "median_file": statistics.median(lines.values()),
        "largest_file": f"{biggest[0]} ({biggest[1]})",
        "functions": len(spans),
        "median_function": statistics.median(n for _, n in spans),
        "longest_function": f"{longest[0]} ({longest[1]})",
        "functions_over_80": sorted(f"{name} ({n})" for name, n in spans if n > LONG_FUNCTION),
        "public_names": len(public),
        "repeated_file_names": sorted(f"{name} ×{n}" for name, n in names.items() if n > 1),
        "import_floors_top_down": floors(edges, rooms),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", default="src/taptr", type=Path)
    parser.add_argument("--json", action="store_true", help="print JSON instead of lines")
    args = parser.parse_args()
    result = measure(args.root)
    if args.json:
        print(json.dumps(result, indent=2))
        return
    for key, value in result.items():
        print(f"{key}: {value}")


if __name__ == "__main__":
    main()
