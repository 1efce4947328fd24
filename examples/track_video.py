"""Track points through a video from Python: what ``taptr track`` does, step by step.

    python examples/track_video.py                  # the generated sample clip, 6x6 grid
    python examples/track_video.py video.mp4 --grid 12 --backward
    python examples/track_video.py video.mp4 --points "0,120,80;10,300.5,42" --backward

Queries are (t, x, y): a frame index, then pixel coordinates of the input video with pixel
centres at integers. Writes OUT/tracks.npz (tracks, visibility, queries, metadata),
OUT/tracks.csv (one row per frame and point) and OUT/overlay.mp4 (points with trails;
rings where a point is predicted occluded).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("video", nargs="?", help="video file or image folder (default: sample)")
    queries = parser.add_mutually_exclusive_group()
    queries.add_argument("--points", help='queries "t,x,y;t,x,y;..." in pixels')
    queries.add_argument("--grid", type=int, default=6, help="N×N grid on frame 0 (default 6)")
    parser.add_argument("--backward", action="store_true", help="also track before each query")
    parser.add_argument(
        "--checkpoint",
        help="checkpoint file or model name (default: the paper's weights taptrv2-official, "
        "non-commercial licence; offline, the bundled taptr-small-synthetic)",
    )
    parser.add_argument("--device", help="cpu, cuda, mps (default: cuda if available)")
    parser.add_argument("--max-frames", type=int, help="read at most this many frames")
    parser.add_argument("--out", default="outputs/track_video", help="output folder")
    return parser.parse_args(argv)


def main(argv: Sequence[str] | None = None) -> int:
    """Tracks and writes the three files."""
    args = parse_args(argv)
    import numpy as np

    import taptr
    from taptr.io.tracks import save_tracks_csv, save_tracks_npz
    from taptr.io.video import read_video, video_info, write_video
    from taptr.viz.draw import draw_tracks

    if args.video:
        video = read_video(args.video, max_frames=args.max_frames)  # (T, H, W, 3) uint8 RGB
        fps = video_info(args.video).fps or 24.0
    else:
        from taptr.data.sample_video import make_sample_clip

        clip = make_sample_clip(num_frames=args.max_frames or 48)
        video, fps = clip.video, clip.fps
    num_frames, height, width = video.shape[:3]

    if args.points:
        rows = [r for r in args.points.split(";") if r.strip()]
        queries = np.array([[float(v) for v in r.split(",")] for r in rows], np.float32)
    else:
        # a grid inset from the borders, all queried on frame 0
        xs = np.linspace(0.1 * (width - 1), 0.9 * (width - 1), args.grid)
        ys = np.linspace(0.1 * (height - 1), 0.9 * (height - 1), args.grid)
        queries = np.array([[0, x, y] for y in ys for x in xs], np.float32)

    predictor = taptr.Predictor.from_pretrained(args.checkpoint, device=args.device)
    result = predictor.track(video, queries, backward=args.backward)
    tracks = result.tracks[0].numpy()  # (T, N, 2) (x, y) pixels
    visible = result.visibility[0].numpy()  # (T, N) bool

    out = Path(args.out)
    metadata = {"video": args.video or "sample clip", "width": width, "height": height}
    save_tracks_npz(out / "tracks.npz", tracks, visible, queries, metadata)
    save_tracks_csv(out / "tracks.csv", tracks, visible)
    # without --backward, frames before a query are not tracked: draw from the query frame
    starts = None if args.backward else queries[:, 0].astype(np.int64)
    write_video(out / "overlay.mp4", draw_tracks(video, tracks, visible, query_frames=starts), fps)

    print(f"{len(queries)} points, {num_frames} frames of {width}x{height}; wrote {out}/")
    for n, (t, x, y) in enumerate(queries[:5]):
        x_last, y_last = tracks[-1, n]
        seen = visible[int(t) :, n].mean()
        print(
            f"  ({x:.1f}, {y:.1f}) on frame {int(t)} -> ({x_last:.1f}, {y_last:.1f}), "
            f"visible on {100 * seen:.0f}% of its frames"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
