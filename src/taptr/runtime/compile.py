"""Optional ``torch.compile`` of the model's heavy parts for inference.

`compile_model` compiles the backbone, the input projections, the encoder and the decoder
in place (``nn.Module.compile``), leaving the Python window loop as it is. The first
windows are slow (compilation, and one recompilation when the frame count per encoder
call or the point count changes); afterwards the same tracker runs the compiled code.
Outputs equal the eager model's up to float rounding. Measured speed-ups are in
``docs/EXPORT.md``; on CPU they are modest, so nothing compiles unless asked.
"""

from __future__ import annotations

from taptr.model.taptr import TAPTR


def compile_model(
    model: TAPTR,
    *,
    mode: str | None = None,
    dynamic: bool | None = None,
    backend: str = "inductor",
) -> TAPTR:
    """Compiles the model's backbone, input projections, encoder and decoder in place.

    Args:
        model: the network; returned for chaining (``Predictor(compile_model(model))``).
        mode: ``torch.compile`` mode (None, ``"reduce-overhead"``, ``"max-autotune"``).
        dynamic: ``torch.compile``'s dynamic-shape setting (None: specialise first, then
            generalise the sizes that change).
        backend: ``torch.compile``'s backend (``inductor`` generates code; ``eager`` only
            traces, which tests use to check the traced model quickly).
    """
    for part in (model.backbone, model.input_projections, model.encoder, model.decoder):
        part.compile(mode=mode, dynamic=dynamic, backend=backend)
    return model
