"""The rooms keep to what they hold: imports checked module by module in fresh processes.

- `taptr.task` and `taptr.onnx` run without torch: every module imports in a process where
  ``import torch`` fails;
- `taptr.export` builds and checks graphs: no module of it imports onnxruntime or OpenVINO
  when imported (an engine loads only when a graph is run);
- no class is defined in two source files.
"""

from __future__ import annotations

import ast
import json
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import pytest

import taptr

IMPORT_ALL = """
import importlib, json, pkgutil, sys
for blocked in filter(None, sys.argv[2].split(",")):
    sys.modules[blocked] = None  # importing it now raises ImportError
package = importlib.import_module(sys.argv[1])
names = [info.name for info in pkgutil.walk_packages(package.__path__, package.__name__ + ".")]
for name in names:
    importlib.import_module(name)
loaded = [n for n in ("torch", "onnxruntime", "openvino") if sys.modules.get(n) is not None]
print(json.dumps({"modules": names, "loaded": loaded}))
"""


def _import_every_module(package: str, blocked: str = "") -> dict:
    run = subprocess.run(
        [sys.executable, "-c", IMPORT_ALL, package, blocked],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    return json.loads(run.stdout.splitlines()[-1])


@pytest.mark.parametrize("package", ["taptr.task", "taptr.onnx"])
def test_runner_rooms_import_no_torch(package):
    imported = _import_every_module(package, blocked="torch")
    assert len(imported["modules"]) >= 5
    assert imported["loaded"] == []  # no torch, and no engine until one is opened


def test_export_imports_no_engine():
    imported = _import_every_module("taptr.export")
    assert "taptr.export.v3_graphs" in imported["modules"]
    assert imported["loaded"] == ["torch"]


def test_no_class_is_defined_twice():
    root = Path(taptr.__file__).parent
    defined = defaultdict(list)
    for path in sorted(root.rglob("*.py")):
        for node in ast.parse(path.read_text()).body:
            if isinstance(node, ast.ClassDef):
                defined[node.name].append(str(path.relative_to(root)))
    twice = {name: files for name, files in defined.items() if len(files) > 1}
    assert not twice
