"""The Ray cluster of a corpus job: reaching it, sizing the actors, leaving nothing behind.

Everything Ray would wait on forever is checked first, in seconds: an address that
answers nothing, actors that no node can hold (more CPUs or GPUs than any node has, a GPU
on a cluster without one), more actors than the cluster holds, actors whose models
would not fit in their nodes' memory. Each is a one-line error with the numbers.
"""

from __future__ import annotations

import builtins
import contextlib
import logging
import math
import os
import signal
import socket
from collections.abc import Iterator
from dataclasses import dataclass
from types import ModuleType
from typing import TYPE_CHECKING, Any

from taptr.messages import error_line

if TYPE_CHECKING:
    from taptr.api.predictor import Predictor

CONNECT_SECONDS = 10.0
"""How long the cluster's address may take to accept a connection."""

PROCESS_BYTES = 768 * 2**20
"""A tracker actor's process before any video: Python, PyTorch, Ray's worker, the model's
code (about 600 MiB resident measured on CPU actors)."""

TYPICAL_FRAMES, TYPICAL_SIZE, TYPICAL_POINTS = 300, (720, 1280), 256
"""The clip an actor's memory is sized for: 10 s of 720p at 30 fps, 256 query points."""


@dataclass(frozen=True)
class ActorShape:
    """What one tracker actor reserves.

    Attributes:
        cpus: CPUs (CPU actors run as many torch threads).
        gpus: GPUs (fractions share one).
        memory: bytes of host memory (Ray's ``memory`` resource).
    """

    cpus: float
    gpus: float
    memory: int


def require_ray() -> ModuleType:
    """Imports Ray (and checks pyarrow), or says how to install them."""
    try:
        import pyarrow  # noqa: F401
        import ray
    except ModuleNotFoundError:
        raise ModuleNotFoundError(
            'tracking a corpus needs Ray: pip install -e ".[ray]" in a checkout of taptr '
            '(pip install "taptr[ray]" once taptr is on the package index)'
        ) from None
    return ray


def check_address(address: str | None) -> None:
    """Fails fast when a cluster's address does not accept connections.

    Args:
        address: ``HOST:PORT``, ``ray://HOST:PORT``, ``auto``, ``local`` or None (then
            ``RAY_ADDRESS``, else a local instance).

    Raises:
        ValueError: nothing answers there within `CONNECT_SECONDS` (one line, named).
    """
    address = address or os.environ.get("RAY_ADDRESS")
    if not address or address in ("auto", "local"):
        return
    where = address.split("://", 1)[-1]
    host, _, port = where.rpartition(":")
    if not host or not port.isdigit():
        raise ValueError(f"--address {address}: expected HOST:PORT, ray://HOST:PORT or auto")
    try:
        socket.create_connection((host.strip("[]"), int(port)), CONNECT_SECONDS).close()
    except OSError as error:
        reason = error.strerror or error_line(error)
        raise ValueError(f"cannot reach the Ray cluster at {address}: {reason}") from None


@contextlib.contextmanager
def joined(ray: ModuleType, address: str | None) -> Iterator[None]:
    """Joins the cluster (or starts a local instance) for the block, and leaves it.

    A local instance started here is stopped at the end, Ctrl-C and SIGTERM included,
    so that no Ray process of the job outlives it. The process's own SIGINT and SIGTERM
    handlers are kept (Ray's would end the process with a native stack), and its
    ``print``: Ray swaps in its own when it prints a worker's death, and leaves it.

    Raises:
        ValueError: the cluster refuses the connection (one line).
    """
    check_address(address)
    handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    own_print = builtins.print
    started_here = not ray.is_initialized()
    if started_here:
        try:
            ray.init(
                address=address,
                log_to_driver=False,  # the actors' lines are in Ray's logs; ours are events
                logging_level=logging.WARNING,
                configure_logging=True,
            )
        except (ConnectionError, ray.exceptions.RayError, RuntimeError) as error:
            where = address or os.environ.get("RAY_ADDRESS") or "a local instance"
            raise ValueError(
                f"cannot join the Ray cluster ({where}): {error_line(error)}"
            ) from None
    _restore(handlers)
    try:
        yield
    finally:
        if started_here:
            ray.shutdown()
        _restore(handlers)
        builtins.print = own_print


def actor_memory(predictor: Predictor) -> int:
    """Bytes one tracker actor needs: its process and a typical clip's run (`TYPICAL_FRAMES`)."""
    from taptr.memory_estimate import estimate_tracking

    config = predictor.model.config
    weights = sum(p.numel() * p.element_size() for p in predictor.model.parameters())
    if config is None:
        return PROCESS_BYTES + weights
    run = estimate_tracking(
        config,
        input_size=predictor.input_size,
        num_frames=TYPICAL_FRAMES,
        num_points=TYPICAL_POINTS + predictor.context_points,
        frame_size=TYPICAL_SIZE,
        whole_video=False,
    )
    return PROCESS_BYTES + weights + run.total


def plan_actors(ray: ModuleType, actors: int | None, shape: ActorShape) -> int:
    """How many actors to start: ``actors``, checked against the cluster; None: all it holds.

    Raises:
        ValueError: no node holds one actor, or the cluster holds fewer than ``actors``
            (one line with the numbers).
    """
    nodes = [node["Resources"] for node in ray.nodes() if node.get("Alive")]
    fits = [_fits(resources, shape) for resources in nodes]
    capacity = sum(fits)
    asked = _describe(shape)
    if capacity == 0:
        empty: dict[str, float] = {}
        largest = max(nodes, key=lambda r: (r.get("GPU", 0), r.get("CPU", 0)), default=empty)
        raise ValueError(
            f"no node of the cluster can hold one tracker actor ({asked}); the largest has "
            f"{_have(largest)}: lower --cpus-per-actor, --gpus-per-actor or "
            "--memory-per-actor, or add nodes"
        )
    if actors is not None and actors > capacity:
        raise ValueError(
            f"--actors {actors} ({asked} each) is more than the cluster holds: {capacity} "
            f"on {len(nodes)} node(s); ask for at most {capacity}"
        )
    return capacity if actors is None else actors


def _fits(resources: dict[str, float], shape: ActorShape) -> int:
    """Actors of ``shape`` one node holds."""
    bounds = [
        resources.get("CPU", 0.0) / shape.cpus if shape.cpus else math.inf,
        resources.get("GPU", 0.0) / shape.gpus if shape.gpus else math.inf,
        resources.get("memory", 0.0) / shape.memory if shape.memory else math.inf,
    ]
    least = min(bounds)
    return 0 if least == math.inf else int(least + 1e-9)


def _describe(shape: ActorShape) -> str:
    gpus = f", {shape.gpus:g} GPU" if shape.gpus else ""
    return f"{shape.cpus:g} CPU{gpus}, {shape.memory / 2**30:.1f} GiB"


def _have(resources: dict[str, float]) -> str:
    gpus = f", {resources.get('GPU', 0):g} GPU" if resources.get("GPU") else ", no GPU"
    memory = resources.get("memory", 0) / 2**30
    return f"{resources.get('CPU', 0):g} CPU{gpus}, {memory:.1f} GiB"


def _restore(handlers: dict[signal.Signals, Any]) -> None:
    for number, handler in handlers.items():
        if handler is not None:
            signal.signal(number, handler)  # type: ignore[arg-type]
