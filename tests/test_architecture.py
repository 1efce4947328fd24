"""docs/ARCHITECTURE.md's floors hold the imports: the page fails here when the code moves.

The table "The rooms, top down" lists every room of ``src/taptr`` (a package folder such as
``model/``, or a top-level module such as ``config``) on a floor; rows with an empty floor
cell share the floor above. The import graph between rooms (every ``import`` in the
source, those inside functions and ``TYPE_CHECKING`` blocks included: each is a
dependency) must have no cycle, and each import must point to a lower floor, except on
the ground floor, whose plain modules may use one another.
"""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PAGE = ROOT / "docs" / "ARCHITECTURE.md"
PACKAGE = ROOT / "src" / "taptr"


def _tree_metrics():
    spec = importlib.util.spec_from_file_location("tree_metrics", ROOT / "scripts/tree_metrics.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def documented_floors() -> list[tuple[str, list[str]]]:
    """(floor, rooms) of the table, top down."""
    text = PAGE.read_text()
    table = text.split("## The rooms, top down", 1)[1].split("\n## ", 1)[0]
    floors: list[tuple[str, list[str]]] = []
    for line in table.splitlines():
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        if len(cells) < 3 or cells[0] in ("floor", "---") or (set(cells[0]) <= {"-"} and cells[0]):
            continue
        rooms = re.findall(r"`([\w/]+)`", cells[1])
        if cells[0]:
            floors.append((cells[0], rooms))
        else:
            floors[-1][1].extend(rooms)
    return floors


def test_every_room_is_on_one_floor():
    rooms = _tree_metrics().room_graph(PACKAGE)[0]
    listed = [room for _, rooms in documented_floors() for room in rooms]
    assert sorted(set(listed)) == sorted(listed), "a room is listed twice"
    assert sorted(rooms - {"__init__"}) == sorted(listed)


def test_imports_point_down_the_floors():
    _, edges, witnesses = _tree_metrics().room_graph(PACKAGE)
    floors = documented_floors()
    height = {room: -i for i, (_, rooms) in enumerate(floors) for room in rooms}
    name = {room: floor for floor, rooms in floors for room in rooms}
    ground = floors[-1][0]

    def allowed(room: str, target: str) -> bool:
        return height[target] < height[room] or (
            height[target] == height[room] == -(len(floors) - 1)
        )

    wrong = [
        f"{room} ({name[room]}) imports {target} ({name[target]}): {witnesses[room, target]}"
        for room, targets in edges.items()
        for target in sorted(targets)
        if room in height and target in height and not allowed(room, target)
    ]
    assert not wrong, f"docs/ARCHITECTURE.md's floors (ground: {ground}) disagree:\n" + "\n".join(
        wrong
    )


def test_the_rooms_have_no_import_cycle():
    metrics = _tree_metrics()
    rooms, edges, _ = metrics.room_graph(PACKAGE)
    floors = metrics.floors(edges, rooms, strict=True)
    assert sum(len(f) for f in floors) == len(rooms)


def test_the_code_keeps_no_benchmark_history():
    """Comments say why; the dated measurements of particular hosts live in the docs.

    A host name or a date in the source is a measurement that will go stale there
    (docs/BENCHMARKS.md and BENCHMARKS_LOG.md keep them with their commands);
    `model/ops/cpu_features` names CPUs to explain ``TAPTR_CPU``, not to report speeds.
    """
    history = re.compile(r"\b20\d\d-\d\d-\d\d\b|\b(EPYC|Xeon|Ryzen|Graviton)\b")
    found = [
        f"{path.relative_to(PACKAGE)}:{number}: {line.strip()}"
        for path in sorted(PACKAGE.rglob("*.py"))
        if path.name != "cpu_features.py"
        for number, line in enumerate(path.read_text().splitlines(), 1)
        if history.search(line)
    ]
    assert not found, "benchmark history in the code:\n" + "\n".join(found)


def test_the_package_top_level_keeps_at_most_ten_loose_modules():
    """Loose modules are the ground's few shared rules; a component belongs in a room."""
    loose = sorted(p.stem for p in PACKAGE.glob("*.py") if p.name != "__init__.py")
    assert len(loose) <= 10, f"{len(loose)} loose modules at src/taptr's top level: {loose}"
