"""Where the decoder's cross-attention puts its weight, relative to the tracked point.

TAPTRv2's motivation for the attention-based position update (APU) is that the key-aware
cross-attention weights concentrate on the samples that lie where the point really is, so
their weighted offsets tell where to move it. This module measures that on any model and
video: while a `Predictor` tracks query points, forward hooks read every decoder layer's
cross-attention output (`taptr.model.attention.DeformableOutput`: pre-softmax logits and
sampling offsets) without changing any computation, and the weights (the softmax over each
head's L·P samples, as the attention computes it) are binned by the offset of their sample
from the point's reference position of that layer.

Only the analysed points count (never the predictor's context points), on the frames where
they are being tracked (after their query frame, the decoder's ``update`` mask), in every
window that decodes them. Offsets are in pixels of the model input (``input_size``): a
level-l offset o moves the sample by o / (W_l, H_l) in normalised units, i.e.
o · (W_in − 1) / W_l pixels.

`attention_statistics` turns the records into numbers (JSON-ready), `draw_attention` into a
figure (OpenCV only, so no plotting library is needed).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np
import torch
from torch import Tensor, nn

DISTANCE_EDGES = (0.0, 1.0, 2.0, 4.0, 8.0, 16.0, 32.0, math.inf)
"""Bin edges (model-input pixels) of the distance between a sample and its point."""


@dataclass
class AttentionRecord:
    """Cross-attention weights of one decoder layer, gathered over windows.

    Attributes:
        weights: per decoder call, (E, M, L, P) attention weights of the E kept entries
            (point × frame), summing to 1 over (L, P) for each head.
        offsets: per decoder call, (E, M, L, P, 2) sample offsets (dx, dy) from the point's
            reference, in model-input pixels.
    """

    weights: list[np.ndarray] = field(default_factory=list)
    offsets: list[np.ndarray] = field(default_factory=list)

    def stacked(self) -> tuple[np.ndarray, np.ndarray]:
        """All entries: weights (E, M, L, P) and offsets (E, M, L, P, 2)."""
        if not self.weights:
            raise ValueError("no attention was recorded for this layer")
        return np.concatenate(self.weights), np.concatenate(self.offsets)


@contextlib.contextmanager
def record_cross_attention(
    model: nn.Module, input_size: tuple[int, int], num_points: int | None = None
) -> Iterator[list[AttentionRecord]]:
    """Records the decoder's cross-attention while the block runs; hooks only read.

    Args:
        model: a `taptr.model.taptr.TAPTR` (anything with ``decoder.layers[i].cross_attention``).
        input_size: (H_in, W_in) of the model input, to express offsets in its pixels.
        num_points: keep only the first this many points of each call (the predictor puts
            its context points after the user's); None keeps all.

    Yields:
        one `AttentionRecord` per decoder layer, filled as decoder calls happen.
    """
    decoder: Any = model.decoder
    layers = list(decoder.layers)
    records = [AttentionRecord() for _ in layers]
    masks: list[Tensor] = []  # the update mask of the decoder call in progress
    height, width = input_size

    def on_decoder(module: nn.Module, args: tuple[Any, ...], kwargs: dict[str, Any]) -> None:
        update = kwargs["update"] if "update" in kwargs else args[5]  # (B, W_t, N)
        masks[:] = [update.flatten(0, 1)]  # (B·W_t, N): entries after their query frame

    def on_cross(index: int) -> Any:
        def hook(module: nn.Module, args: tuple[Any, ...], output: Any) -> None:
            spatial_shapes = args[3]
            logits, offsets = output.logits.detach().float(), output.offsets.detach().float()
            keep = masks[0] if masks else torch.ones(logits.shape[:2], dtype=torch.bool)
            if num_points is not None:
                logits, offsets = logits[:, :num_points], offsets[:, :num_points]
                keep = keep[:, :num_points]
            keep = keep.to(logits.device)
            entries, heads, levels, points = logits[keep].shape
            weights = logits[keep].reshape(entries, heads, -1).softmax(-1)
            sizes = offsets.new_tensor([[w, h] for h, w in spatial_shapes])  # (L, 2) (W_l, H_l)
            scale = offsets.new_tensor([width - 1, height - 1])
            pixels = offsets[keep] / sizes[:, None, :] * scale  # (E, M, L, P, 2)
            records[index].weights.append(
                weights.view(entries, heads, levels, points).cpu().numpy()
            )
            records[index].offsets.append(pixels.cpu().numpy())

        return hook

    handles = [decoder.register_forward_pre_hook(on_decoder, with_kwargs=True)]
    handles += [
        layer.cross_attention.register_forward_hook(on_cross(i)) for i, layer in enumerate(layers)
    ]
    try:
        yield records
    finally:
        for handle in handles:
            handle.remove()


def analyze_attention(
    predictor: Any,
    video: np.ndarray | Tensor,
    queries: np.ndarray | Tensor,
) -> list[AttentionRecord]:
    """Tracks ``queries`` through ``video`` and returns each decoder layer's attention.

    Args:
        predictor: a `taptr.api.predictor.Predictor`.
        video: (T, H, W, 3) uint8 frames (anything `Predictor.track` accepts for one video).
        queries: (N, 3) (t, x, y) queries in video pixels.

    Returns:
        one `AttentionRecord` per decoder layer.
    """
    num_points = int(torch.as_tensor(queries).reshape(-1, 3).shape[0])
    with record_cross_attention(predictor.model, predictor.input_size, num_points) as records:
        predictor.track(video, queries)
    return records


def _histogram_bins(radius: float, bins: int) -> np.ndarray:
    return np.linspace(-radius, radius, bins + 1)


def attention_statistics(
    records: list[AttentionRecord], radius: float | None = None, bins: int = 33
) -> dict[str, Any]:
    """Per-layer numbers of the recorded attention (fractions, pixels of the model input).

    For each layer: how many entries, the mean distance of the samples from the point and
    the attention-weighted one, the attention mass and the share of samples per distance
    bin (`DISTANCE_EDGES`; mass above share means the weight goes to those samples more
    than to others), the mass per feature level, the normalised entropy of each head's
    weights (1: uniform over its L·P samples, 0: all on one), the mean largest weight,
    the mean length of each head's weighted mean offset (the move the APU would read
    without its disentangler), and a 2-D histogram of the mass over (dx, dy).

    Args:
        records: one per decoder layer, from `record_cross_attention` or `analyze_attention`.
        radius: half-width of the 2-D histogram in pixels; default: the 95th percentile of
            the sample distances of all layers, rounded up to a whole pixel.
        bins: cells per side of the 2-D histogram.

    Returns:
        ``{"distance_edges", "histogram_radius", "histogram_bins", "layers": [...]}``.
    """
    stacked = [record.stacked() for record in records]
    if radius is None:
        distances = np.concatenate([np.linalg.norm(o, axis=-1).ravel() for _, o in stacked])
        radius = float(max(1.0, math.ceil(np.percentile(distances, 95))))
    edges = _histogram_bins(radius, bins)
    layers = []
    for index, (weights, offsets) in enumerate(stacked):
        entries, heads, levels, points = weights.shape
        # each entry-head is a distribution over its L·P samples; averaging over them gives
        # the share of attention per sample of the typical head
        mass = weights / (entries * heads)
        distance = np.linalg.norm(offsets, axis=-1)  # (E, M, L, P)
        share = np.full_like(mass, 1.0 / mass.size)
        flat_w = weights.reshape(entries, heads, -1)
        entropy = -(flat_w * np.log(np.clip(flat_w, 1e-12, None))).sum(-1) / math.log(
            levels * points
        )
        weighted = (flat_w[..., None] * offsets.reshape(entries, heads, -1, 2)).sum(2)  # (E,M,2)
        histogram, _, _ = np.histogram2d(
            offsets[..., 1].ravel(), offsets[..., 0].ravel(), [edges, edges], weights=mass.ravel()
        )
        samples, _, _ = np.histogram2d(
            offsets[..., 1].ravel(), offsets[..., 0].ravel(), [edges, edges]
        )
        layers.append(
            {
                "layer": index,
                "entries": int(entries),
                "heads": int(heads),
                "levels": int(levels),
                "points_per_level": int(points),
                "mean_sample_distance": float(distance.mean()),
                "attention_weighted_distance": float((mass * distance).sum()),
                "mass_by_distance": _binned(distance, mass),
                "samples_by_distance": _binned(distance, share),
                "mass_by_level": [float(m) for m in mass.sum((0, 1, 3))],
                # coarse levels sample far from the point in pixels: distances per level
                "sample_distance_by_level": [float(d) for d in distance.mean((0, 1, 3))],
                "weighted_distance_by_level": [
                    float(d)
                    for d in (mass * distance).sum((0, 1, 3))
                    / np.maximum(mass.sum((0, 1, 3)), 1e-12)
                ],
                "normalised_entropy": float(entropy.mean()),
                "max_weight": float(flat_w.max(-1).mean()),
                "weighted_offset_length": float(np.linalg.norm(weighted, axis=-1).mean()),
                "mass_outside_histogram": float(max(0.0, 1.0 - histogram.sum())),
                "histogram": np.round(histogram, 6).tolist(),  # rows: dy, columns: dx
                "sample_histogram": (samples / max(samples.sum(), 1)).round(6).tolist(),
            }
        )
    return {
        "offset_unit": "pixels of the model input",
        "distance_edges": [e if math.isfinite(e) else None for e in DISTANCE_EDGES],
        "histogram_radius": radius,
        "histogram_bins": bins,
        "layers": layers,
    }


def _binned(distance: np.ndarray, amount: np.ndarray) -> list[float]:
    """Sum of ``amount`` per `DISTANCE_EDGES` bin of ``distance``."""
    index = np.digitize(distance.ravel(), DISTANCE_EDGES[1:-1])
    return [float(v) for v in np.bincount(index, amount.ravel(), len(DISTANCE_EDGES) - 1)]


def draw_attention(statistics: dict[str, Any], title: str = "", cell: int = 200) -> np.ndarray:
    """A figure of `attention_statistics`: one heat map per layer and a distance profile.

    Top row: the attention mass over (dx, dy) per decoder layer, on a log colour scale,
    the point at the centre (white cross). Bottom: per layer, the attention mass per
    distance bin (filled bars) against the share of samples in that bin (outlines).

    Args:
        statistics: the output of `attention_statistics`.
        title: a line drawn at the top.
        cell: side of each heat map in pixels.

    Returns:
        (H, W, 3) uint8 RGB image.
    """
    layers = statistics["layers"]
    count = len(layers)
    margin, header, chart = 12, 40, 200
    width = max(count * (cell + margin) + margin, 640)
    height = header + cell + 30 + chart + 60
    canvas = np.full((height, width, 3), 255, np.uint8)
    font = cv2.FONT_HERSHEY_SIMPLEX
    black = (0, 0, 0)
    cv2.putText(canvas, title, (margin, 22), font, 0.5, black, 1, cv2.LINE_AA)
    colours = _layer_colours(count)
    radius = statistics["histogram_radius"]
    for i, layer in enumerate(layers):
        mass = np.asarray(layer["histogram"], np.float64)
        scaled = np.log10(mass + 1e-5)  # four decades of attention mass
        scaled = (scaled - scaled.min()) / max(scaled.max() - scaled.min(), 1e-9)
        heat = cv2.applyColorMap((255 * scaled).astype(np.uint8), cv2.COLORMAP_INFERNO)
        heat = cv2.resize(heat, (cell, cell), interpolation=cv2.INTER_NEAREST)[..., ::-1]
        left = margin + i * (cell + margin)
        canvas[header : header + cell, left : left + cell] = heat
        mid = (left + cell // 2, header + cell // 2)
        cv2.drawMarker(canvas, mid, (255, 255, 255), cv2.MARKER_CROSS, 10, 1)
        label = f"layer {layer['layer']}: {layer['attention_weighted_distance']:.1f} px"
        cv2.putText(canvas, label, (left, header + cell + 16), font, 0.4, colours[i], 1)
    cv2.putText(
        canvas,
        f"heat maps: +/-{radius:g} px around the point, log mass; "
        "bars: mass (filled) vs samples (outline) per distance bin",
        (margin, header - 6),
        font,
        0.35,
        black,
        1,
        cv2.LINE_AA,
    )
    _draw_profile(canvas, layers, statistics["distance_edges"], colours, header + cell + 30, chart)
    return canvas


def _layer_colours(count: int) -> list[tuple[int, int, int]]:
    hues = np.linspace(0, 150, max(count, 1), endpoint=False).astype(np.uint8)
    hsv = np.stack([hues, np.full_like(hues, 220), np.full_like(hues, 180)], -1)[None]
    rgb = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0]
    return [(int(r), int(g), int(b)) for r, g, b in rgb]


def _draw_profile(
    canvas: np.ndarray,
    layers: list[dict[str, Any]],
    edges: list[float | None],
    colours: list[tuple[int, int, int]],
    top: int,
    chart: int,
) -> None:
    """Grouped bars: per distance bin, each layer's mass (filled) and sample share (outline)."""
    font = cv2.FONT_HERSHEY_SIMPLEX
    left, right = 40, canvas.shape[1] - 12
    bins = len(edges) - 1
    highest = max(max(*x["mass_by_distance"], *x["samples_by_distance"]) for x in layers)
    group = (right - left) / bins
    bar = max(2, int(group / (len(layers) + 1)))
    bottom = top + chart
    cv2.line(canvas, (left, bottom), (right, bottom), (0, 0, 0), 1)
    for level in (0.25, 0.5, 0.75, 1.0):
        y = int(bottom - level * chart)
        cv2.line(canvas, (left - 4, y), (left, y), (0, 0, 0), 1)
        cv2.putText(canvas, f"{level * highest:.2f}", (2, y + 4), font, 0.3, (0, 0, 0), 1)
    for b in range(bins):
        x0 = left + int(b * group)
        high = edges[b + 1]
        label = f"{edges[b]:g}-{high:g}" if high is not None else f">{edges[b]:g}"
        cv2.putText(canvas, label + " px", (x0 + 4, bottom + 14), font, 0.33, (0, 0, 0), 1)
        for i, layer in enumerate(layers):
            x = x0 + 4 + i * bar
            mass = layer["mass_by_distance"][b] / highest
            share = layer["samples_by_distance"][b] / highest
            cv2.rectangle(
                canvas, (x, int(bottom - mass * chart)), (x + bar - 2, bottom), colours[i], -1
            )
            cv2.rectangle(
                canvas, (x, int(bottom - share * chart)), (x + bar - 2, bottom), (0, 0, 0), 1
            )
