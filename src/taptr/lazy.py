"""Names a package hands on, imported when first used (a module ``__getattr__``, PEP 562).

`taptr`, `taptr.api` and `taptr.export` name what users import from them without importing
it: torch, the exporters or onnxruntime load only with the first name that needs them.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from typing import Any


def lazy_names(package: str, exports: dict[str, str]) -> Callable[[str], Any]:
    """The ``__getattr__`` of ``package``, importing each name's module on first use.

    Args:
        package: the package's name, for the error.
        exports: name → the module that defines it.
    """

    def attribute(name: str) -> Any:
        module = exports.get(name)
        if module is None:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        return getattr(importlib.import_module(module), name)

    return attribute
