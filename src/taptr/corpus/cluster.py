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

from taptr.messages import error_line, install_line

if TYPE_CHECKING:
    from taptr.corpus.model_facts import ModelFacts

logger = logging.getLogger(__name__)

LOOPBACK_SWITCH = "RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"
"""Ray's variable that, at ``0``, keeps a node's address and ports on loopback."""

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
        raise ModuleNotFoundError(f"tracking a corpus needs Ray: {install_line('ray')}") from None
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

    A local instance started here listens on loopback only (`on_loopback`) and is stopped
    at the end, Ctrl-C and SIGTERM included, so that no Ray process of the job outlives
    it. The process's own SIGINT and SIGTERM handlers are kept (Ray's would end the
    process with a native stack), and its ``print``: Ray swaps in its own when it prints a
    worker's death, and leaves it. Those lines (``(raylet) A worker died ...``) go to the
    debug log: the job counts deaths itself.

    Raises:
        ValueError: the cluster refuses the connection (one line).
    """
    check_address(address)
    handlers = {number: signal.getsignal(number) for number in (signal.SIGINT, signal.SIGTERM)}
    own_print = builtins.print
    started_here = not ray.is_initialized()
    local = started_here and starts_local(address)
    with _worker_deaths_logged():
        if started_here:
            # a cluster on loopback is joined as one: Ray would name it by the host's address
            loopback = local or on_loopback_host(address or os.environ.get("RAY_ADDRESS"))
            with on_loopback() if loopback else contextlib.nullcontext():
                _init(ray, address)
        _restore(handlers)
        if local:
            _say_if_exposed(ray)
        try:
            yield
        finally:
            if started_here:
                ray.shutdown()
            _restore(handlers)
            builtins.print = own_print


def starts_local(address: str | None) -> bool:
    """Whether ``ray.init(address=address)`` starts a local instance rather than joining one."""
    if address is None:
        return not os.environ.get("RAY_ADDRESS")
    return address == "local"


def on_loopback_host(address: str | None) -> bool:
    """Whether ``address`` (``HOST:PORT``) names a cluster on this host's loopback."""
    import ipaddress

    if not address or "://" in address or ":" not in address:
        return False  # auto, local, Ray Client (ray://): Ray resolves them itself
    host = address.rpartition(":")[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@contextlib.contextmanager
def on_loopback() -> Iterator[None]:
    """Ray instances started in the block give their node 127.0.0.1: every port on loopback.

    Ray 2.60 gives a node the host's network address, and its gcs_server, raylet,
    workers and driver then listen on every interface; ``ray.init(_node_ip_address=
    "127.0.0.1")`` and ``--node-ip-address=127.0.0.1`` are turned back into the host's
    address (``resolve_ip_for_localhost``). It keeps a node on loopback only where
    multi-node clusters are off: `LOOPBACK_SWITCH` ``=0``, its default on Windows and
    macOS. The processes started in the block inherit the variable; the driver's copy of
    the switch, read when Ray was imported, is set for the block.
    """
    import importlib

    try:
        constants: Any = importlib.import_module("ray._private.ray_constants")
    except ImportError:  # another Ray: the variable alone, and `_say_if_exposed` checks
        constants = None
    saved_variable = os.environ.get(LOOPBACK_SWITCH)
    saved = getattr(constants, "ENABLE_RAY_CLUSTER", None)
    os.environ[LOOPBACK_SWITCH] = "0"
    if saved is not None:
        constants.ENABLE_RAY_CLUSTER = False
    try:
        yield
    finally:
        if saved is not None:
            constants.ENABLE_RAY_CLUSTER = saved
        if saved_variable is None:
            os.environ.pop(LOOPBACK_SWITCH, None)
        else:
            os.environ[LOOPBACK_SWITCH] = saved_variable


def _init(ray: ModuleType, address: str | None) -> None:
    try:
        ray.init(
            address=address,
            log_to_driver=False,  # the actors' lines are in Ray's logs; ours are events
            logging_level=logging.ERROR,  # its token-authentication notice: docs/CORPUS.md
            configure_logging=True,
        )
    except (ConnectionError, ray.exceptions.RayError, RuntimeError) as error:
        where = address or os.environ.get("RAY_ADDRESS") or "a local instance"
        raise ValueError(f"cannot join the Ray cluster ({where}): {error_line(error)}") from None


def _say_if_exposed(ray: ModuleType) -> None:
    """One line when a local instance could not be kept on loopback, and what to do."""
    import ipaddress

    node = ray.util.get_node_ip_address()
    with contextlib.suppress(ValueError):
        if ipaddress.ip_address(node.strip("[]")).is_loopback:
            return
    logger.warning(
        "the local Ray instance listens on %s, not only on loopback: its ports are open to "
        "the network; block them with a firewall, or start Ray on a trusted network "
        "yourself and pass --address (docs/CORPUS.md, What a cluster exposes)",
        node,
    )


@contextlib.contextmanager
def _worker_deaths_logged() -> Iterator[None]:
    """Ray's lines about dead workers to the debug log instead of the job's stdout.

    The driver's error listener prints them (``(raylet) A worker died or was killed
    ...``) even with ``log_to_driver=False``, through ``print_to_stdstream``.
    """
    import importlib

    try:
        worker: Any = importlib.import_module("ray._private.worker")
    except ImportError:
        worker = None
    original = getattr(worker, "print_to_stdstream", None)
    if original is None:
        yield
        return

    def to_log(data: dict[str, Any], ignore_prefix: bool = False) -> None:
        for line in data.get("lines", []):
            logger.debug("ray (%s): %s", data.get("pid"), line)

    worker.print_to_stdstream = to_log
    try:
        yield
    finally:
        worker.print_to_stdstream = original


def actor_memory(facts: ModelFacts) -> int:
    """Bytes one tracker actor needs: its process, weights and a typical clip's run.

    Args:
        facts: the tracker (`taptr.corpus.model_facts`): its config, input size, context
            points and weights' size, read without building it.
    """
    from taptr.memory_estimate import estimate_tracking

    run = estimate_tracking(
        facts.config,
        input_size=facts.input_size,
        num_frames=TYPICAL_FRAMES,
        num_points=TYPICAL_POINTS + facts.context_points,
        frame_size=TYPICAL_SIZE,
        whole_video=False,
    )
    return PROCESS_BYTES + facts.weight_bytes + run.total


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
