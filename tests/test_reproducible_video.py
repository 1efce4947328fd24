"""Written videos are the same bytes every time (issue 30, item 3: ``taptr edit`` differed).

x264's macroblock-tree rate control read memory it had not written, so the same frames gave
different files once the process had freed other data: two ``taptr edit`` runs on a real
clip differed by up to 56/255 per pixel. Each encoding here runs in a fresh interpreter
whose C heap was first filled with different noise and freed, as a long tracking run
leaves it.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

ENCODE = """
import ctypes, sys
import cv2, numpy as np
from taptr.data.photos import load_builtin_photos
from taptr.io.video import write_video

photo = load_builtin_photos("train")[0]
# a hand-held camera: a slow pan and zoom over a photograph (plain noise does not show it)
frames = [
    cv2.warpAffine(photo, np.array([[1 + 0.01 * t, 0, -3 * t], [0, 1 + 0.01 * t, -2 * t]]),
                   (320, 240), flags=cv2.INTER_LINEAR)
    for t in range(12)
]
libc = ctypes.CDLL(None)
libc.malloc.restype, libc.malloc.argtypes = ctypes.c_void_p, [ctypes.c_size_t]
libc.free.argtypes = [ctypes.c_void_p]
rng = np.random.default_rng(int(sys.argv[1]))
blocks = []
for size in rng.integers(1 << 10, 1 << 20, 300):
    noise = rng.integers(0, 256, int(size), np.uint8)
    blocks.append(libc.malloc(int(size)))
    ctypes.memmove(blocks[-1], noise.ctypes.data, int(size))
for block in blocks:
    libc.free(block)
write_video(sys.argv[2], iter(frames), 10.0)
"""


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fills glibc's heap")
def test_the_same_frames_encode_to_the_same_bytes_whatever_memory_held(tmp_path):
    pytest.importorskip("sklearn", reason="the photographs come with scikit-learn")
    for seed in (1, 2):
        done = subprocess.run(
            [sys.executable, "-c", ENCODE, str(seed), str(tmp_path / f"{seed}.mp4")],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert done.returncode == 0, done.stderr[-2000:]
    assert (tmp_path / "1.mp4").read_bytes() == (tmp_path / "2.mp4").read_bytes()
