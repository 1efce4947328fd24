"""The message for a torchvision that was built for another torch.

PyTorch and torchvision are released in pairs, and each torchvision wheel loads compiled
operators built against one torch version and one CUDA (or CPU) variant. Installed from
different indexes or at different times (a CPU torch beside a CUDA torchvision), importing
torchvision fails with "operator torchvision::nms does not exist", which names neither
package nor the remedy. `torchvision_mismatch` says both.
"""

from __future__ import annotations

from importlib import metadata

import torch


def _version(package: str) -> str:
    try:
        return metadata.version(package)
    except metadata.PackageNotFoundError:
        return "(unknown version)"


def torchvision_mismatch(error: BaseException) -> str:
    """One line: the two versions, torchvision's own error, and how to install a pair."""
    reason = " ".join(str(error).split())[:160]
    return (
        f"torchvision {_version('torchvision')} does not match torch {torch.__version__} "
        f"(importing it failed: {reason}); install a matching pair from one index, e.g. "
        "pip install --force-reinstall torch torchvision --index-url "
        "https://download.pytorch.org/whl/cpu (or /whl/cu124 for CUDA 12.4)"
    )
