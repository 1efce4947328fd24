"""``taptr track-corpus`` on a Ray cluster of three nodes on this machine, one lost mid-run.

A head node (no CPUs for actors) and two worker nodes of one CPU each, on loopback
(`ray.cluster_utils.Cluster` under `taptr.corpus.cluster.on_loopback`: no Ray process
listens or connects beyond it, checked mid-run); the job joins through ``--address``
with one actor per worker node. Once the first part is written, a whole worker node is
removed (its raylet and every worker on it end, as when a machine is lost). The job must
end with every video done exactly once or recorded as failed, on the node that is left.
"""

from __future__ import annotations

import contextlib
import io
import threading
import time

import pytest

from taptr.cli.main import main
from taptr.io.video import write_video
from tests.corpus_helpers import ray_sockets_beyond_loopback
from tests.helpers import panning_clip

ray = pytest.importorskip("ray")
pq = pytest.importorskip("pyarrow.parquet")


@pytest.fixture
def cluster(monkeypatch):
    from ray.cluster_utils import Cluster

    from taptr.corpus.cluster import on_loopback

    monkeypatch.setenv("RAY_memory_monitor_refresh_ms", "0")
    with on_loopback():  # Ray would give each node the host's address, ports open to all
        built = Cluster(
            initialize_head=True, head_node_args={"num_cpus": 0, "include_dashboard": False}
        )
        workers = [built.add_node(num_cpus=1) for _ in range(2)]
    built.wait_for_nodes()
    yield built, workers
    if ray.is_initialized():
        ray.shutdown()
    built.shutdown()


def test_a_worker_node_lost_mid_run_loses_no_video_and_duplicates_none(
    cluster, tiny_checkpoint, tmp_path
):
    built, workers = cluster
    clips = tmp_path / "clips"
    clips.mkdir()
    for index in range(16):
        write_video(clips / f"c{index:02d}.mp4", panning_clip(12, 1, index), fps=10)
    out = tmp_path / "out"
    lost = threading.Event()
    exposed: list[str] = []

    def lose_a_node() -> None:
        deadline = time.monotonic() + 300
        while time.monotonic() < deadline:
            if (out / "_index").is_dir() and any((out / "_index").iterdir()):
                exposed.extend(ray_sockets_beyond_loopback())  # every node, actors running
                built.remove_node(workers[1])
                lost.set()
                return
            time.sleep(0.05)

    killer = threading.Thread(target=lose_a_node, daemon=True)
    killer.start()
    printed = io.StringIO()
    argv = [
        "track-corpus", str(clips), "--grid", "2", "--checkpoint", str(tiny_checkpoint),
        "--device", "cpu", "--out", str(out), "--address", built.address, "--actors", "2",
        "--part-videos", "2", "--actor-start-timeout", "120", "--progress-every", "0",
    ]  # fmt: skip
    with contextlib.redirect_stdout(printed):
        status = main(argv)
    killer.join(timeout=5)
    assert lost.is_set(), printed.getvalue()
    assert exposed == []  # gcs_server, raylets, workers, the driver: loopback only
    # Ray's own lines (the lost node's raylet, its last log lines) stay in its logs
    said = printed.getvalue().splitlines()
    assert all(line.startswith(("corpus: ", "16 videos: ")) for line in said), said
    assert status == 0, printed.getvalue()
    assert "16 videos: 16 done" in printed.getvalue()
    index = pq.read_table(out / "_index")["video_id"].to_pylist()
    expected = sorted(str(clips / f"c{i:02d}.mp4") for i in range(16))
    assert sorted(index) == expected  # each video committed exactly once
    rows = pq.read_table(out / "tracks")["video_id"].to_pylist()
    assert sorted(rows) == sorted(expected * 4)  # and its 4 rows written exactly once
    alive = [node for node in ray.nodes() if node["Alive"]] if ray.is_initialized() else None
    assert alive is None or len(alive) == 2
