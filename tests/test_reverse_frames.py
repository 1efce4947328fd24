"""Reading a video backwards, segment by segment, gives the forward frames in reverse."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from taptr.io import reverse_frames
from taptr.io.reverse_frames import iter_frames_reversed
from taptr.io.video import read_video, write_video


def _frames(count: int) -> np.ndarray:
    rng = np.random.default_rng(0)
    frames = (rng.random((count, 32, 48, 3)) * 255).astype(np.uint8)
    frames[:, :8, :8] = np.arange(count)[:, None, None, None] * 4  # a mark per frame
    return frames


@pytest.fixture(scope="module")
def clip(tmp_path_factory):
    return write_video(tmp_path_factory.mktemp("rev") / "clip.mp4", _frames(40), fps=24)


@pytest.mark.parametrize(("segment", "max_frames"), [(7, None), (1, 5), (64, 23)])
def test_reversed_video_equals_the_forward_frames_reversed(clip, segment, max_frames):
    forward = read_video(clip, max_frames=max_frames)
    backward = np.stack(list(iter_frames_reversed(clip, segment=segment, max_frames=max_frames)))
    np.testing.assert_array_equal(backward, forward[::-1])


def test_segments_are_found_by_seeking(clip, monkeypatch):
    decoded_from_start = []
    original = reverse_frames._segment_from_start
    monkeypatch.setattr(
        reverse_frames,
        "_segment_from_start",
        lambda *args: decoded_from_start.append(args) or original(*args),
    )
    assert len(list(iter_frames_reversed(clip, segment=8))) == 40
    assert decoded_from_start == []  # every segment came from a seek


def test_without_seeking_every_segment_is_decoded_from_the_start(clip, monkeypatch):
    monkeypatch.setattr(reverse_frames, "_segment_by_seeking", lambda *args: None)
    backward = np.stack(list(iter_frames_reversed(clip, segment=9)))
    np.testing.assert_array_equal(backward, read_video(clip)[::-1])


def test_gif_and_image_folder(tmp_path):
    frames = [np.full((16, 24, 3), 8 * t, np.uint8) for t in range(12)]
    images = [Image.fromarray(f) for f in frames]
    images[0].save(tmp_path / "a.gif", save_all=True, append_images=images[1:], duration=40)
    gif = np.stack(list(iter_frames_reversed(tmp_path / "a.gif", segment=5)))
    np.testing.assert_array_equal(gif, read_video(tmp_path / "a.gif")[::-1])
    folder = tmp_path / "frames"
    folder.mkdir()
    for t, image in enumerate(images):
        image.save(folder / f"f{t}.png")
    backward = np.stack(list(iter_frames_reversed(folder, max_frames=10)))
    np.testing.assert_array_equal(backward, np.stack(frames[:10])[::-1])


def test_bad_arguments_and_files(tmp_path, clip):
    with pytest.raises(ValueError, match="segment must be >= 1"):
        iter_frames_reversed(clip, segment=0)
    with pytest.raises(FileNotFoundError, match="video not found"):
        iter_frames_reversed(tmp_path / "missing.mp4")
    broken = tmp_path / "broken.mp4"
    broken.write_bytes(b"not a video at all")
    with pytest.raises(ValueError, match="cannot read video"):
        list(iter_frames_reversed(broken))
