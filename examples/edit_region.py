"""Track a painted region and paste an image onto it: what ``taptr edit`` does, in Python.

    python examples/edit_region.py        # sample clip: a logo stuck on the rolling disc
    python examples/edit_region.py video.mp4 --mask region.png --overlay logo.png

The mask is a PNG of the video's size, white inside the region, drawn on ``--query-frame``.
Points are sampled on a grid inside it (`taptr.api.regions.sample_region_queries`), tracked
forwards and backwards in time, and on every frame the region's motion is fitted to the
visible points (a RANSAC homography, outliers dropped) and the overlay is warped with it;
it is hidden on frames where too few points are visible (the region is occluded).
Without arguments the sample clip is used, with the rolling disc as the region and a
generated checkerboard as the overlay. Writes ``--out`` (H.264 mp4).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

import numpy as np


def parse_args(argv: Sequence[str] | None) -> argparse.Namespace:
    """The command line."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("video", nargs="?", help="video file or image folder (default: sample)")
    parser.add_argument("--mask", help="PNG mask of the region (required with a video)")
    parser.add_argument("--overlay", help="RGB or RGBA image (default: a checkerboard)")
    parser.add_argument("--query-frame", type=int, default=0, help="frame the mask was drawn on")
    parser.add_argument("--stride", type=int, default=6, help="pixels between tracked points")
    parser.add_argument("--max-frames", type=int, help="read at most this many frames")
    parser.add_argument(
        "--checkpoint",
        help="checkpoint file or model name (default: the paper's weights taptrv2-official, "
        "non-commercial licence; offline, the bundled taptr-small-synthetic)",
    )
    parser.add_argument("--device", help="cpu, cuda, mps (default: cuda if available)")
    parser.add_argument("--out", default="outputs/edited.mp4", help="output mp4")
    return parser.parse_args(argv)


def checkerboard(size: int = 64, squares: int = 4) -> np.ndarray:
    """(size, size, 4) RGBA checkerboard, opaque, orange and blue."""
    cells = (np.indices((size, size)) * squares // size).sum(axis=0) % 2
    image = np.where(cells[..., None] == 1, [255, 140, 0, 255], [30, 80, 220, 255])
    return image.astype(np.uint8)


def main(argv: Sequence[str] | None = None) -> int:
    """Tracks the region and writes the edited video."""
    args = parse_args(argv)
    import taptr
    from taptr.api.regions import read_mask, sample_region_queries
    from taptr.apps.editing import overlay_region
    from taptr.io.video import read_video, video_info, write_video

    if args.video:
        if not args.mask:
            raise SystemExit("--mask is required with a video")
        video = read_video(args.video, max_frames=args.max_frames)  # (T, H, W, 3) RGB
        fps = video_info(args.video).fps or 24.0
        mask = read_mask(args.mask)  # (H, W) bool
    else:
        from taptr.data.sample_video import make_sample_clip

        clip = make_sample_clip(num_frames=args.max_frames or 48)
        video, fps = clip.video, clip.fps
        # the occluding disc on the query frame, shrunk a little to stay off its edge
        cx, cy = clip.disc_centers()[args.query_frame]
        ys, xs = np.mgrid[: video.shape[1], : video.shape[2]]
        mask = np.hypot(xs - cx, ys - cy) <= 0.8 * clip.disc_radius
    if args.overlay:
        from PIL import Image

        overlay = np.asarray(Image.open(args.overlay).convert("RGBA"))  # keeps transparency
    else:
        overlay = checkerboard()

    queries = sample_region_queries(mask, args.query_frame, stride=args.stride)
    predictor = taptr.Predictor.from_pretrained(args.checkpoint, device=args.device)
    result = predictor.track(video, queries, backward=True)  # every frame, both directions
    tracks, visible = result.tracks[0].numpy(), result.visibility[0].numpy()
    edited = overlay_region(video, overlay, mask, tracks, visible, args.query_frame)
    path = write_video(args.out, edited, fps)
    shown = (visible.mean(axis=1) >= 0.5).sum()
    print(f"tracked {len(queries)} region points; overlay shown on {shown} of {len(video)} frames")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
