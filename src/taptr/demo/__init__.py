"""The web demo behind ``taptr demo``: a Gradio app for tracking points and editing videos.

The package is split so that everything but the page itself is plain, testable Python:

- `taptr.demo.settings`: the limits and server defaults (light, read by the CLI parser);
- `taptr.demo.inputs`: reading uploaded videos and bundled samples, clicked points,
  painted masks, and turning them into (t, x, y) queries;
- `taptr.demo.handlers`: the two jobs the page runs (tracking, editing), each a plain
  function of the predictor API that writes its outputs into a fresh folder;
- `taptr.demo.app`: the Gradio page, a thin layer that wires components to the handlers;
- `taptr.demo.launch`: the private temporary workspace and the server's lifetime.

Only `app` imports Gradio, so ``import taptr`` and ``taptr --help`` never do. The demo uses
the API layer only (`taptr.api`, `taptr.viz`, `taptr.editing`, `taptr.data.sample_video`).
"""
