"""Parts of a corpus's output folder written without Ray, and the paths a run touches.

Shared by the tests of tampered folders (tests/test_corpus_tampered.py) and the fuzz
category of tampered folders (tests/fuzz_corpus.py).
"""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from taptr.corpus.records import Failure, VideoTracks

RUN = "20261207T000000000000Z"
DIGEST = "d" * 16


def video(name: str, frames: int = 4, points: int = 3, digest: str = DIGEST) -> VideoTracks:
    """A tracked video of ``points`` rows with seeded values."""
    rng = np.random.default_rng(len(name) + frames)
    return VideoTracks(
        video_id=name,
        path=f"/clips/{name}.mp4",
        queries=np.zeros((points, 3), np.float32),
        tracks=rng.random((frames, points, 2), np.float32),
        visibility=rng.random((frames, points)) > 0.3,
        size=(32, 48),
        fps=10.0,
        declared_frames=frames,
        model="tiny",
        digest=digest,
    )


def failure(name: str, digest: str = DIGEST) -> Failure:
    """A failed video's record."""
    return Failure(name, f"/clips/{name}.mp4", "cannot read video", 1, 48, 6, digest)


def prepared(out: Path):
    """The layout of ``out``, prepared as a run prepares it."""
    from taptr.corpus.layout import ResultLayout

    layout = ResultLayout.at(str(out))
    layout.prepare()
    return layout


def write_part(layout, names: str | list[str], failed: tuple[str, ...] = (), run: str = RUN) -> str:
    """Publishes one part holding ``names`` (done) and ``failed``; returns its name."""
    from taptr.corpus.parts import PartWriter

    writer = PartWriter(layout, run)
    for index, name in enumerate(names):
        writer.add_tracks(index, video(name))
    for index, name in enumerate(failed, len(names)):
        writer.add_failure(index, failure(name))
    return writer.flush().part


@contextlib.contextmanager
def touched_paths() -> Iterator[list[str]]:
    """Every filesystem path a corpus's storage makes in the block (`Storage.path`).

    Storage is the one place paths are made from OUT and a name; pyarrow then opens,
    renames and removes them in C++, out of Python's audit hooks' sight.
    """
    from taptr.corpus.storage import Storage

    made: list[str] = []
    original = Storage.path

    def recorded(self: Storage, relative: str) -> str:
        path = original(self, relative)
        made.append(path)
        return path

    Storage.path = recorded  # type: ignore[method-assign]
    try:
        yield made
    finally:
        Storage.path = original  # type: ignore[method-assign]


def inside(path: str, out: Path) -> bool:
    """Whether ``path`` is ``out`` or lies in it, links and ``..`` resolved."""
    root = os.path.realpath(out)
    resolved = os.path.realpath(path)
    return resolved == root or resolved.startswith(root + os.sep)


def snapshot(folder: Path) -> dict[str, bytes]:
    """Every file below ``folder`` (links not followed) and its bytes."""
    found = {}
    for path in sorted(folder.rglob("*")):
        if path.is_file() and not path.is_symlink():
            found[str(path.relative_to(folder))] = path.read_bytes()
    return found


def ray_sockets_beyond_loopback(root: int | None = None) -> list[str]:
    """Listening or connected sockets of ``root``'s process tree not on loopback.

    Args:
        root: the process whose tree is checked (default: this one, whose children are
            the Ray processes a local instance or `ray.cluster_utils.Cluster` starts).

    Returns:
        ``"process: address"`` for every listening socket bound beyond loopback and every
        connection to a peer beyond it (empty when all of the tree's traffic is local).
    """
    import psutil

    top = psutil.Process(root or os.getpid())
    family = {top.pid: top.name()}
    for child in top.children(recursive=True):
        with contextlib.suppress(psutil.Error):
            family[child.pid] = child.name()
    found = []
    for connection in psutil.net_connections(kind="inet"):
        if connection.pid not in family:
            continue
        bound = connection.status == psutil.CONN_LISTEN or connection.type == socket.SOCK_DGRAM
        ends = [connection.laddr] if bound and connection.laddr else []
        ends += [connection.raddr] if connection.raddr else []
        found += [
            f"{family[connection.pid]}: {end.ip}:{end.port} ({connection.status})"
            for end in ends
            if not _loopback(end.ip)
        ]
    return found


def _loopback(address: str) -> bool:
    import ipaddress

    ip = ipaddress.ip_address(address.split("%")[0])
    mapped = getattr(ip, "ipv4_mapped", None)
    return ip.is_loopback or (mapped is not None and mapped.is_loopback)


@contextlib.contextmanager
def s3_on_loopback(**environment: str) -> Iterator[str | None]:
    """An S3-compatible server (moto) on a free loopback port; its URI parameters, or None.

    ``environment`` goes to the server (``INITIAL_NO_AUTH_ACTION_COUNT="0"`` makes it check
    credentials). None when the server did not start.
    """
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    server = subprocess.Popen(
        [sys.executable, "-m", "moto.server", "-p", str(port)],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        env={**os.environ, **environment},
    )
    try:
        for _ in range(100):
            with contextlib.suppress(OSError):
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                yield f"endpoint_override=127.0.0.1:{port}&scheme=http"
                return
            time.sleep(0.1)
        yield None
    finally:
        server.terminate()
        server.wait(timeout=10)
