"""What a tracker is made of, as a small picklable record: `ModelSpec`.

A spec names the checkpoint and how it runs (device, precision, options). It holds no
model and imports no torch, so a command can check it, digest it and hand it to another
process (a corpus actor) before anything heavy loads; `ModelSpec.load` builds the
tracker it describes in the process that calls it.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from taptr.api.graph_predictor import GraphPredictor
    from taptr.api.predictor import Predictor


@dataclass(frozen=True)
class ModelSpec:
    """A tracker described without building it.

    Attributes:
        checkpoint: a checkpoint file or model name; None: the default model
            (`taptr.weights.registry.DEFAULT_MODEL`, else the bundled one with a warning).
        device: ``cpu``, ``cuda``, ``cuda:N``, ``mps``; None: the best this machine has.
        dtype: the precision of the model's products: ``float32`` (no autocast),
            ``bfloat16`` or ``float16`` (autocast, weights kept in float32); with a graph
            engine, the engine's precision (`taptr.onnx.precisions`): ``float32``,
            ``bfloat16`` (OpenVINO) or ``int8`` (the encoder quantised once).
        input_size: (H, W) the model sees; None: the model's.
        context_points: TAPTRv2's context points K; None: the model's.
        support: extra points around the queries (`taptr.config.SUPPORT_KINDS`);
            None: the model's own.
        history_frames: TAPTRv3's held past frames (0: all); None: the model's.
        kernel: the deformable-attention kernel (`taptr.runtime.kernel_choice`).
        frames_per_call: frames per encoder call, or ``auto``.
        capture: TAPTRv3's captured step: ``auto``, ``on`` or ``off``.
        compile: compile the model with ``torch.compile``.
        threads: CPU threads for products and convolutions; None: the free cores
            (`taptr.runtime.threads.choose_threads`). A graph engine gets them too
            (onnxruntime's intra-op threads, OpenVINO's inference threads).
        engine: what runs the tracker (`taptr.types.ENGINE_CHOICES`): ``torch``, or
            TAPTRv3's exported graphs in ``onnxruntime`` or ``openvino``, exported once per
            checkpoint and kept (`taptr.export.cache`); the same tracks up to float
            rounding. The graph engines run on the CPU in ``dtype`` as the engine's
            precision and ignore ``kernel``, ``frames_per_call``, ``capture`` and ``compile``.
    """

    checkpoint: str | None = None
    device: str | None = None
    dtype: str = "float32"
    input_size: tuple[int, int] | None = None
    context_points: int | None = None
    support: str | None = None
    history_frames: int | None = None
    kernel: str = "auto"
    frames_per_call: int | str = "auto"
    capture: str = "auto"
    compile: bool = False
    threads: int | None = None
    engine: str = "torch"

    def on(self, device: str | None) -> ModelSpec:
        """The same tracker on another device."""
        return replace(self, device=device)

    def load(self) -> Predictor | GraphPredictor:
        """The predictor this spec describes, built in this process.

        Raises:
            ValueError: a graph engine asked for a TAPTR v1 or v2 checkpoint, or an
                unknown engine.
        """
        if self.engine != "torch":
            from taptr.api.graph_predictor import load_graph_predictor

            return load_graph_predictor(self)
        from taptr.api.predictor import Predictor
        from taptr.runtime.precision import autocast_type
        from taptr.runtime.threads import use_threads

        use_threads(self.threads)
        predictor = Predictor.from_pretrained(
            self.checkpoint,
            device=self.device,
            input_size=self.input_size,
            context_points=self.context_points,
            support_points=self.support,
            history_frames=self.history_frames,
            autocast=autocast_type(self.dtype),
            kernel=self.kernel,
            frames_per_call=self.frames_per_call,
            capture=self.capture,
        )
        if self.compile:
            from taptr.runtime.compile import compile_model

            compile_model(predictor.model)
        return predictor
