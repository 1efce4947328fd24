"""Video reading and writing on tiny videos fabricated in the test, plus the shared samples."""

from __future__ import annotations

import av
import cv2
import numpy as np
import pytest
from PIL import Image

from taptr.io.video import (
    iter_frames,
    natural_sort_key,
    read_video,
    video_info,
    write_video,
)
from tests.helpers import SHARED_MEDIA


def _ramp_video(num_frames: int = 6, height: int = 32, width: int = 48) -> np.ndarray:
    """Smooth frames (codec-friendly) whose mean brightness encodes the frame index."""
    x = np.linspace(0, 60, width)[None, :, None]
    frames = [np.broadcast_to(x + 30 * t, (height, width, 3)) for t in range(num_frames)]
    return np.clip(np.stack(frames), 0, 255).astype(np.uint8)


def _encode(path, frames: np.ndarray, codec: str, fps: int = 10, rotation: int = 0) -> None:
    with av.open(str(path), "w") as container:
        stream = container.add_stream(codec, rate=fps)
        stream.width, stream.height, stream.pix_fmt = frames.shape[2], frames.shape[1], "yuv420p"
        if rotation:
            stream.set_display_rotation(rotation)
        for frame in frames:
            container.mux(stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")))
        container.mux(stream.encode())


def test_write_then_read_round_trip(tmp_path):
    frames = _ramp_video()
    path = write_video(tmp_path / "out.mp4", frames, fps=12.5)
    info = video_info(path)
    assert (info.num_frames, info.fps, info.height, info.width) == (6, 12.5, 32, 48)
    decoded = read_video(path)
    assert decoded.shape == frames.shape and decoded.dtype == np.uint8
    assert np.abs(decoded.astype(int) - frames).mean() < 3
    assert [p.name for p in tmp_path.iterdir()] == ["out.mp4"]  # no temporary file left


def test_write_uses_the_fast_x264_preset(tmp_path):
    path = write_video(tmp_path / "out.mp4", _ramp_video(), fps=10)
    settings = path.read_bytes().split(b"options: ", 1)[1].split(b"\x00", 1)[0]  # x264's SEI
    # veryfast: subpixel refinement 2 and one reference frame (medium: subme=7 ref=3)
    assert b" subme=2 " in settings and b" ref=1 " in settings and b"crf=18.0" in settings


def test_write_pads_odd_sizes_and_accepts_a_generator(tmp_path):
    frames = _ramp_video(height=31, width=45)
    path = write_video(tmp_path / "odd.mp4", (f for f in frames), fps=10)
    decoded = read_video(path)
    assert decoded.shape == (6, 32, 46, 3)
    assert np.abs(decoded[:, :31, :45].astype(int) - frames).mean() < 3


def test_write_failure_leaves_nothing(tmp_path):
    def frames():
        yield _ramp_video()[0]
        raise RuntimeError("producer failed")

    with pytest.raises(RuntimeError):
        write_video(tmp_path / "out.mp4", frames(), fps=10)
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ValueError, match="all frames must be 48x32"):
        write_video(tmp_path / "out.mp4", [_ramp_video()[0], _ramp_video(width=40)[0]], fps=10)
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("frames", "suffix", "fps", "message"),
    [
        ([], ".mp4", 10, "no frames"),
        (np.zeros((2, 8, 8), np.uint8), ".mp4", 10, "uint8 RGB"),
        (np.zeros((2, 8, 8, 3), np.float32), ".mp4", 10, "uint8 RGB"),
        (np.zeros((2, 8, 8, 3), np.uint8), ".avi", 10, "mp4"),
        (np.zeros((2, 8, 8, 3), np.uint8), ".mp4", 0, "fps"),
    ],
)
def test_write_rejects_bad_input(tmp_path, frames, suffix, fps, message):
    with pytest.raises(ValueError, match=message):
        write_video(tmp_path / f"out{suffix}", frames, fps=fps)


@pytest.mark.parametrize(("suffix", "codec"), [(".webm", "libvpx-vp9"), (".avi", "mpeg4")])
def test_reads_other_containers(tmp_path, suffix, codec):
    frames = _ramp_video()
    _encode(tmp_path / f"clip{suffix}", frames, codec)
    decoded = read_video(tmp_path / f"clip{suffix}")
    assert decoded.shape == frames.shape
    assert np.abs(decoded.astype(int) - frames).mean() < 6
    assert video_info(tmp_path / f"clip{suffix}").fps == 10


def test_reads_gif(tmp_path):
    frames = _ramp_video()
    images = [Image.fromarray(f) for f in frames]
    images[0].save(tmp_path / "clip.gif", save_all=True, append_images=images[1:], duration=100)
    decoded = read_video(tmp_path / "clip.gif")
    assert decoded.shape == frames.shape
    assert np.abs(decoded.astype(int) - frames).mean() < 6  # palette quantisation


def test_stride_and_max_frames(tmp_path):
    frames = _ramp_video(num_frames=8)
    path = write_video(tmp_path / "clip.mp4", frames, fps=10)
    decoded = read_video(path, stride=3, max_frames=2)
    means = decoded.reshape(2, -1).mean(axis=1)
    assert np.allclose(means, frames[[0, 3]].reshape(2, -1).mean(axis=1), atol=3)
    assert len(list(iter_frames(path, stride=3))) == 3  # frames 0, 3, 6


def test_display_rotation_is_applied(tmp_path):
    frames = np.zeros((2, 32, 48, 3), np.uint8)
    frames[:, :8, :8] = 255  # a white top-left corner
    _encode(tmp_path / "rotated.mp4", frames, "libx264", rotation=90)
    info = video_info(tmp_path / "rotated.mp4")
    assert (info.height, info.width) == (48, 32)
    upright = read_video(tmp_path / "rotated.mp4")[0]
    # A quarter turn counter-clockwise moves the top-left corner to the bottom-left.
    assert upright[-4, 4].mean() > 200 and upright[4, 4].mean() < 50


def test_image_folder_in_natural_order(tmp_path):
    frames = _ramp_video(num_frames=11)
    for t, frame in enumerate(frames):  # frame_2.png must come before frame_10.png
        cv2.imwrite(str(tmp_path / f"frame_{t}.png"), cv2.cvtColor(frame, cv2.COLOR_RGB2BGR))
    (tmp_path / "notes.txt").write_text("ignored")
    np.testing.assert_array_equal(read_video(tmp_path), frames)
    np.testing.assert_array_equal(read_video(tmp_path, stride=5, max_frames=2), frames[[0, 5]])
    info = video_info(tmp_path)
    assert (info.num_frames, info.fps, info.height, info.width) == (11, None, 32, 48)
    assert sorted(["b10", "b2", "a3"], key=natural_sort_key) == ["a3", "b2", "b10"]


def test_image_folder_errors(tmp_path):
    with pytest.raises(ValueError, match="no png/jpg images"):
        read_video(tmp_path)
    cv2.imwrite(str(tmp_path / "0.png"), np.zeros((8, 8, 3), np.uint8))
    cv2.imwrite(str(tmp_path / "1.png"), np.zeros((8, 9, 3), np.uint8))
    with pytest.raises(ValueError, match="first frame is 8x8"):
        read_video(tmp_path)
    (tmp_path / "2.jpg").write_bytes(b"not an image")
    with pytest.raises(ValueError, match=r"2\.jpg: not a readable image"):
        read_video(tmp_path, stride=2)


def test_file_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"missing.mp4"):
        iter_frames(tmp_path / "missing.mp4")  # at the call, before iterating
    (tmp_path / "clip.xyz").write_bytes(b"")
    with pytest.raises(ValueError, match=r"unsupported video type '.xyz'"):
        video_info(tmp_path / "clip.xyz")
    (tmp_path / "garbage.mp4").write_bytes(b"not a video" * 10)
    with pytest.raises(ValueError, match=r"cannot read video .*garbage.mp4"):
        read_video(tmp_path / "garbage.mp4")
    frames = np.random.default_rng(0).integers(0, 256, (10, 32, 48, 3), dtype=np.uint8)
    data = bytearray(write_video(tmp_path / "noise.mp4", frames, fps=10).read_bytes())
    data[len(data) // 2 : len(data) // 2 + len(data) // 10] = bytes(len(data) // 10)
    (tmp_path / "corrupt.mp4").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"cannot decode video .*corrupt.mp4: invalid data"):
        read_video(tmp_path / "corrupt.mp4")
    with pytest.raises(ValueError, match="stride"):
        read_video(tmp_path / "garbage.mp4", stride=0)


def test_zero_frames_and_no_video_stream(tmp_path):
    with av.open(str(tmp_path / "empty.avi"), "w") as container:
        stream = container.add_stream("mpeg4", rate=10)
        stream.width, stream.height, stream.pix_fmt = 16, 16, "yuv420p"
        container.start_encoding()  # header only, no frame
    with pytest.raises(ValueError, match=r"no frames in video .*empty.avi"):
        read_video(tmp_path / "empty.avi")
    with av.open(str(tmp_path / "audio.mp4"), "w") as container:
        container.add_stream("aac", rate=8000)
        container.start_encoding()
    # an empty track is not written at all: nothing in the file says audio or video
    with pytest.raises(ValueError, match=r"no frames in video .*audio.mp4: .*no track"):
        video_info(tmp_path / "audio.mp4")


@pytest.mark.skipif(not SHARED_MEDIA.is_dir(), reason="shared sample media not present")
def test_shared_sample_metadata_and_lazy_read():
    info = video_info(SHARED_MEDIA / "cat.mp4")
    assert (info.num_frames, info.fps, info.height, info.width) == (87, 20.0, 480, 368)
    first = next(iter_frames(SHARED_MEDIA / "cat.mp4"))
    assert first.shape == (480, 368, 3) and first.dtype == np.uint8
    clip = read_video(SHARED_MEDIA / "apple.mp4", stride=10, max_frames=3)
    assert clip.shape == (3, 720, 1296, 3)


def test_write_image_round_trip(tmp_path):
    from taptr.io.video import write_image

    image = np.zeros((6, 9, 3), np.uint8)
    image[2, 3] = (255, 0, 0)
    path = write_image(tmp_path / "frame.png", image)
    back = read_video(tmp_path)[0]
    assert back.shape == (6, 9, 3) and tuple(back[2, 3]) == (255, 0, 0)
    assert path.name == "frame.png"
    with pytest.raises(ValueError, match="can only write"):
        write_image(tmp_path / "frame.bmp", image)
