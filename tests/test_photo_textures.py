"""Real-photo textures in the synthetic generator: exact tracks, the built-in split, the CLI."""

from __future__ import annotations

import importlib.util
import re

import cv2
import numpy as np
import pytest

from taptr.cli.main import main as cli_main
from taptr.data import photos as photos_module
from taptr.data.kubric import list_sequences, read_sequence
from taptr.data.photos import (
    BUILTIN_PHOTOS,
    builtin_sources,
    find_photo,
    load_builtin_photos,
    load_photo_folder,
    photo_texture,
)
from taptr.data.synthetic import SyntheticConfig, make_video
from taptr.messages import install_line
from tests.photo_checks import colour_drift, colours_under, fabricated_photo

CONFIG = SyntheticConfig(height=96, width=128, num_frames=10, num_points=300, objects=(2, 3))


def photo() -> np.ndarray:
    """The fabricated photograph of these tests: no blue anywhere."""
    return fabricated_photo(0, 120, 160, cell=8)


@pytest.fixture(scope="module")
def textured():
    return make_video(np.random.default_rng(5), CONFIG, [photo()], photo_prob=1.0)


def test_photo_texture_crops_and_is_deterministic():
    image = photo()
    one = photo_texture(np.random.default_rng(1), [image], 40, 70)
    assert one.shape == (40, 70, 3) and one.dtype == np.uint8
    np.testing.assert_array_equal(one, photo_texture(np.random.default_rng(1), [image], 40, 70))
    assert (one[..., 2] == 0).all()  # colours come from the photograph
    with pytest.raises(ValueError, match="no photographs"):
        photo_texture(np.random.default_rng(1), [], 40, 70)


def test_every_layer_is_the_photograph(textured):
    assert textured.video.shape == (10, 96, 128, 3)
    # the fabricated photograph has no blue: a procedural layer anywhere would add some
    assert (textured.video[..., 2] == 0).all()
    assert textured.video[..., :2].std() > 10


def test_same_seed_same_video_and_no_photos_unchanged(textured):
    again = make_video(np.random.default_rng(5), CONFIG, [photo()], photo_prob=1.0)
    np.testing.assert_array_equal(again.video, textured.video)
    np.testing.assert_array_equal(again.tracks, textured.tracks)
    # without photographs the random stream, hence the video, is what it always was
    plain = make_video(np.random.default_rng(5), CONFIG)
    np.testing.assert_array_equal(
        plain.video, make_video(np.random.default_rng(5), CONFIG, None).video
    )
    # the geometry is drawn from the same stream either way: only colours differ
    assert not np.array_equal(plain.video, textured.video)


def test_tracks_follow_photo_content(textured):
    """The colour under a point barely changes between two frames where it is visible."""
    colours = colours_under(textured.video, textured.tracks)
    same, other = colour_drift(colours, textured.visible)
    assert same.size > 300
    assert np.median(same) < 0.3 * np.median(other)


def test_occlusions_still_exact(textured):
    x, y = textured.tracks[..., 0], textured.tracks[..., 1]
    inside = (x >= 0) & (x <= 127) & (y >= 0) & (y <= 95)
    assert not (textured.visible & ~inside).any()
    assert textured.visible.any(axis=0).all()
    assert (~textured.visible & inside).sum() > 20


def test_builtin_split_is_disjoint():
    train, heldout = builtin_sources("train"), builtin_sources("heldout")
    assert train and heldout
    assert {s.name for s in train}.isdisjoint(s.name for s in heldout)
    assert {s.path for s in train}.isdisjoint(s.path for s in heldout)
    assert len(train) + len(heldout) == len(BUILTIN_PHOTOS)
    # scikit-image's images are reserved for evaluation elsewhere
    assert all(s.package != "skimage" for s in BUILTIN_PHOTOS)
    with pytest.raises(ValueError):
        builtin_sources("test")  # type: ignore[arg-type]


def test_missing_package_says_what_to_install(monkeypatch):
    monkeypatch.setattr(photos_module.importlib.util, "find_spec", lambda name: None)
    with pytest.raises(ModuleNotFoundError, match=re.escape(install_line("photos"))):
        find_photo(BUILTIN_PHOTOS[0])


@pytest.mark.parametrize("split", ["train", "heldout"])
def test_builtin_photos_when_installed(split):
    for source in builtin_sources(split):
        if importlib.util.find_spec(source.package) is None:
            pytest.skip(f"{source.package} is not installed (optional extra 'photos')")
    photos = load_builtin_photos(split)
    assert photos and all(p.ndim == 3 and p.shape[2] == 3 and p.dtype == np.uint8 for p in photos)
    assert all(min(p.shape[:2]) >= 256 for p in photos)


def test_photo_folder(tmp_path):
    with pytest.raises(FileNotFoundError):
        load_photo_folder(tmp_path / "missing")
    with pytest.raises(FileNotFoundError, match="no images"):
        load_photo_folder(tmp_path)
    cv2.imwrite(str(tmp_path / "b.png"), fabricated_photo(1, 120, 160, cell=8)[..., ::-1])
    cv2.imwrite(str(tmp_path / "a.jpg"), fabricated_photo(2, 120, 160, cell=8)[..., ::-1])
    (tmp_path / "notes.txt").write_text("not an image")
    photos = load_photo_folder(tmp_path)
    assert len(photos) == 2 and photos[0].shape == (120, 160, 3)
    cv2.imwrite(str(tmp_path / "c.png"), np.zeros((8, 8, 3), np.uint8))
    with pytest.raises(ValueError, match="below"):
        load_photo_folder(tmp_path)


def test_cli_textures(tmp_path, capsys):
    folder = tmp_path / "photos"
    folder.mkdir()
    cv2.imwrite(str(folder / "p.png"), photo()[..., ::-1])
    out = tmp_path / "videos"
    args = ["make-synthetic", "--out", str(out), "--videos", "2", "--size", "64", "80"]
    args += ["--frames", "5", "--points", "30", "--textures", str(folder), "--photo-prob", "1"]
    assert cli_main(args) == 0
    assert "textured with 1 photographs" in capsys.readouterr().out
    sequences = list_sequences(out)
    assert len(sequences) == 2
    sample = read_sequence(sequences[0])
    assert sample.video.shape == (5, 64, 80, 3) and (sample.video[..., 2] == 0).all()
    assert cli_main([*args[:-1], "1.5"]) == 2


def test_photo_prob_must_be_a_probability():
    with pytest.raises(ValueError, match="photo_prob"):
        make_video(np.random.default_rng(0), CONFIG, [photo()], photo_prob=1.5)
