"""Track points live on a camera stream with the streaming API (`taptr.api.online`).

    python examples/online_camera.py                  # camera 0; the sample clip if none
    python examples/online_camera.py --video clip.mp4 --grid 6 --refresh 24
    python examples/online_camera.py --show           # also open a window (needs a display)

Frames are read with OpenCV (``cv2.VideoCapture(0)`` for the first camera) and fed to an
`OnlineTracker` one at a time. Its state is an explicit object: memory stays bounded by
one window however long the stream runs, and a frame's tracks come back once no later
window can change them (about one 8-frame window behind the newest frame). With
``--refresh K``, every K frames the points that are not visible any more are removed and
a fresh grid is added on the newest frame, which is how a camera tracker keeps going.

Writes the drawn stream to ``--out`` (MPEG-4 part 2, which OpenCV's wheel can encode).
Stop a camera stream with Ctrl-C or ``--max-frames``.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import cv2


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--video", help="read this file instead of the camera")
    parser.add_argument("--camera", type=int, default=0, help="camera index (default 0)")
    parser.add_argument("--grid", type=int, default=5, help="N×N points per grid (default 5)")
    parser.add_argument("--refresh", type=int, default=0, help="renew lost points every K frames")
    parser.add_argument("--max-frames", type=int, default=300, help="stop after this many frames")
    parser.add_argument(
        "--checkpoint",
        help="checkpoint file or model name (default: the paper's weights taptrv2-official, "
        "non-commercial licence; offline, the bundled taptr-small-synthetic)",
    )
    parser.add_argument("--device", help="cpu, cuda, mps (default: cuda if available)")
    parser.add_argument("--out", default="outputs/online.mp4", help="drawn stream (mp4)")
    parser.add_argument("--show", action="store_true", help="show the stream in a window")
    return parser.parse_args(argv)


def open_stream(args: argparse.Namespace, scratch: Path) -> cv2.VideoCapture:
    """The camera, or the --video file, or the sample clip (written to ``scratch``)."""
    import cv2

    if args.video is None:
        # OpenCV logs its own "[ WARN:0@...] can't open camera" lines when there is none;
        # the message below says it once, in words
        level = cv2.utils.logging.getLogLevel()
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
        try:
            capture = cv2.VideoCapture(args.camera)
        finally:
            cv2.utils.logging.setLogLevel(level)
        if capture.isOpened():
            print(f"reading camera {args.camera}")
            return capture
        capture.release()
        from taptr.data.sample_video import write_sample_video

        args.video = str(write_sample_video(scratch / "sample.mp4"))
        print(f"no camera {args.camera}: reading the generated sample clip instead")
    capture = cv2.VideoCapture(args.video)
    if not capture.isOpened():
        raise SystemExit(f"cannot open {args.video}")
    return capture


def read_frames(capture: cv2.VideoCapture, max_frames: int) -> Iterator[np.ndarray]:
    """(H, W, 3) uint8 RGB frames until the stream ends or ``max_frames``."""
    import cv2

    for _ in range(max_frames):
        ok, frame = capture.read()
        if not ok:
            return
        yield cv2.cvtColor(frame, cv2.COLOR_BGR2RGB)


def grid(size: int, frame: int, height: int, width: int) -> np.ndarray:
    """(size², 3) queries (t, x, y) on an inset grid of ``frame``."""
    xs = np.linspace(0.1 * (width - 1), 0.9 * (width - 1), size)
    ys = np.linspace(0.1 * (height - 1), 0.9 * (height - 1), size)
    return np.array([[frame, x, y] for y in ys for x in xs], np.float32)


def main(argv: Sequence[str] | None = None) -> int:
    """Streams, tracks, draws."""
    args = parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="taptr-example-") as scratch:
        return run(args, Path(scratch))


def run(args: argparse.Namespace, scratch: Path) -> int:
    """`main` with a scratch folder for the sample clip (when there is no camera)."""
    import cv2

    import taptr
    from taptr.api.online import OnlineTracker, StreamUpdate
    from taptr.viz.draw import draw_frame, point_colors

    predictor = taptr.Predictor.from_pretrained(args.checkpoint, device=args.device)
    online = OnlineTracker(predictor)
    capture = open_stream(args, scratch)
    fps = capture.get(cv2.CAP_PROP_FPS) or 24.0
    waiting: dict[int, np.ndarray] = {}  # frames whose tracks are not final yet
    colors: dict[int, np.ndarray] = {}  # point id -> RGB
    state, writer, count = None, None, 0

    def add_grid(frame_index: int) -> None:
        height, width = state.frame_size
        queries = grid(args.grid, frame_index, height, width)
        ids = online.add_queries(state, queries)
        # colours from the y position in the whole frame, so they do not depend on the others
        for pid, color in zip(ids, point_colors(queries[:, 1:], (0, height - 1)), strict=True):
            colors[pid] = color

    def show(update: StreamUpdate) -> None:
        nonlocal writer
        palette = np.array([colors[pid] for pid in update.point_ids], np.uint8).reshape(-1, 3)
        for k in range(len(update.tracks)):
            frame = waiting.pop(update.first_frame + k)
            tracks = update.tracks[k : k + 1].numpy()  # (1, N, 2): no trail, this frame only
            visible = update.visibility[k : k + 1].numpy()
            active = np.isfinite(update.visibility_logits[k : k + 1].numpy())  # queried yet
            drawn = draw_frame(frame, tracks, visible, palette, active=active | visible)
            if writer is None:
                fourcc = cv2.VideoWriter_fourcc(*"mp4v")
                Path(args.out).parent.mkdir(parents=True, exist_ok=True)
                writer = cv2.VideoWriter(args.out, fourcc, fps, drawn.shape[1::-1])
            writer.write(cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
            if args.show:
                cv2.imshow("taptr", cv2.cvtColor(drawn, cv2.COLOR_RGB2BGR))
                cv2.waitKey(1)

    try:
        for index, frame in enumerate(read_frames(capture, args.max_frames)):
            if state is None:
                state = online.start(frame_size=frame.shape[:2])
                add_grid(0)
            waiting[index] = frame
            update = online.step(state, frame)
            show(update)
            count = index + 1
            if args.refresh and index % args.refresh == 0 and index and len(update.tracks):
                lost = [
                    p for p, v in zip(update.point_ids, update.visibility[-1], strict=True) if not v
                ]
                online.remove_queries(state, lost)
                add_grid(index)  # the newest frame: always after the last decoded window
                print(f"frame {index}: removed {len(lost)} lost points, added {args.grid**2}")
    except KeyboardInterrupt:
        print("stopped")
    finally:
        capture.release()
    if state is None:
        raise SystemExit("the stream had no frames")
    show(online.finish(state))
    if writer is not None:
        writer.release()
    print(f"tracked {count} frames, {len(state.point_ids)} points at the end; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
