"""Track points live on a camera stream with TAPTRv3 exported to ONNX, without torch.

    taptr export --checkpoint taptrv3-official --format onnx --out exported/   # once
    python examples/online_camera_onnx.py --export exported/    # camera 0; the sample clip if none
    python examples/online_camera_onnx.py --export exported/ --video clip.mp4 --grid 6 --refresh 24

The exported graphs run in onnxruntime (or OpenVINO: ``--engine openvino``) through the
torch-free loop (`taptr.onnx.OnnxOnlineTracker`, numpy only): each frame is decoded once
the next one has arrived, so its tracks come back one frame behind the newest. The time
from a frame's arrival to the return of the step is logged for every frame, with a summary
at the end.
With ``--refresh K``, every K frames the points that are not visible any more are removed
and a fresh grid is added on the newest frame, as in ``online_camera.py``, whose camera
and drawing code this script shares. Nothing here imports torch.

Writes the drawn stream to ``--out`` (MPEG-4 part 2). Stop a camera with Ctrl-C or
``--max-frames``.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--export", required=True, help="a TAPTRv3 ONNX export folder")
    parser.add_argument("--video", help="read this file instead of the camera")
    parser.add_argument("--camera", type=int, default=0, help="camera index (default 0)")
    parser.add_argument("--grid", type=int, default=5, help="N×N points per grid (default 5)")
    parser.add_argument("--refresh", type=int, default=0, help="renew lost points every K frames")
    parser.add_argument("--max-frames", type=int, default=300, help="stop after this many frames")
    parser.add_argument("--threads", type=int, default=None, help="the engine's threads")
    parser.add_argument(
        "--engine", default="onnxruntime", choices=("onnxruntime", "openvino"), help="what runs it"
    )
    parser.add_argument("--out", default="outputs/online_onnx.mp4", help="drawn stream (mp4)")
    parser.add_argument("--show", action="store_true", help="show the stream in a window")
    return parser.parse_args(argv)


def camera_code() -> ModuleType:
    """``online_camera.py`` beside this file: its stream opening, frame reading and grid."""
    path = Path(__file__).with_name("online_camera.py")
    spec = importlib.util.spec_from_file_location("taptr_example_online_camera", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


class Drawer:
    """Draws each returned frame with its points and writes (and shows) the stream."""

    def __init__(self, args: argparse.Namespace, fps: float) -> None:
        self.args, self.fps = args, fps
        self.writer: Any = None
        self.colors: dict[int, np.ndarray] = {}  # point id -> RGB

    def color(self, ids: list[int], queries: np.ndarray, height: int) -> None:
        """Colours of new points by their y in the frame."""
        from taptr.viz.draw import point_colors

        for pid, rgb in zip(ids, point_colors(queries[:, 1:], (0, height - 1)), strict=True):
            self.colors[pid] = rgb

    def __call__(self, frame: np.ndarray, update: Any, k: int) -> None:
        """Frame ``k`` of ``update`` over its image (H, W, 3) uint8 RGB."""
        import cv2

        from taptr.viz.draw import draw_frame

        ids = update.point_ids
        palette = np.array([self.colors[pid] for pid in ids], np.uint8).reshape(-1, 3)
        visible = update.visibility[k : k + 1]
        active = np.isfinite(update.visibility_logits[k : k + 1]) | visible  # queried yet
        drawn = draw_frame(frame, update.tracks[k : k + 1], visible, palette, active=active)
        bgr = cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR)
        if self.writer is None:
            Path(self.args.out).parent.mkdir(parents=True, exist_ok=True)
            fourcc = cv2.VideoWriter_fourcc(*"mp4v")
            self.writer = cv2.VideoWriter(self.args.out, fourcc, self.fps, drawn.shape[1::-1])
        self.writer.write(bgr)
        if self.args.show:
            cv2.imshow("taptr (onnx)", bgr)
            cv2.waitKey(1)


def latency_summary(seconds: list[float]) -> str:
    """Median, 90th percentile and worst of the per-frame latencies, in milliseconds."""
    ms = np.array(seconds) * 1000
    return (
        f"latency per frame: median {np.median(ms):.1f} ms, 90th percentile "
        f"{np.percentile(ms, 90):.1f} ms, worst {ms.max():.1f} ms over {len(ms)} frames"
    )


def main(argv: Sequence[str] | None = None) -> int:
    """Streams, tracks, draws, logs the latency."""
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="taptr-example-") as scratch:
        return run(args, Path(scratch))


def run(args: argparse.Namespace, scratch: Path) -> int:
    """`main` with a scratch folder for the sample clip (when there is no camera)."""
    import cv2

    from taptr.onnx import OnnxOnlineTracker, OnnxTracker

    camera = camera_code()
    tracker = OnnxTracker(args.export, engine=args.engine, threads=args.threads)
    online = OnnxOnlineTracker(tracker)
    capture = camera.open_stream(args, scratch)
    draw = Drawer(args, capture.get(cv2.CAP_PROP_FPS) or 24.0)
    waiting: dict[int, np.ndarray] = {}  # frames whose tracks are not back yet
    latencies: list[float] = []
    state, count = None, 0

    def add_grid(frame_index: int) -> None:
        height, width = state.frame_size
        queries = camera.grid(args.grid, frame_index, height, width)
        draw.color(online.add_queries(state, queries), queries, height)

    def show(update: Any) -> None:
        for k in range(len(update.tracks)):
            draw(waiting.pop(update.first_frame + k), update, k)

    try:
        for index, frame in enumerate(camera.read_frames(capture, args.max_frames)):
            if state is None:
                state = online.start(frame_size=frame.shape[:2])
                add_grid(0)
            waiting[index] = frame
            began = time.perf_counter()
            update = online.step(state, frame)
            latencies.append(time.perf_counter() - began)
            print(f"frame {index}: {latencies[-1] * 1000:.1f} ms")
            show(update)
            count = index + 1
            if args.refresh and index and index % args.refresh == 0 and len(update.tracks):
                visible = zip(update.point_ids, update.visibility[-1], strict=True)
                lost = [point for point, seen in visible if not seen]
                online.remove_queries(state, lost)
                add_grid(index)  # the newest frame: never decoded yet
                print(f"frame {index}: removed {len(lost)} lost points, added {args.grid**2}")
    except KeyboardInterrupt:
        print("stopped")
    finally:
        capture.release()
    if state is None:
        raise SystemExit("the stream had no frames")
    show(online.finish(state))
    if draw.writer is not None:
        draw.writer.release()
    print(latency_summary(latencies[1:] or latencies))  # the first pays one-time costs
    print(f"tracked {count} frames, {len(state.point_ids)} points at the end; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
