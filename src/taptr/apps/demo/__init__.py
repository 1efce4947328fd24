"""The web demo behind ``taptr demo``: a Gradio app for tracking points and editing videos.

The package is split so that everything but the page itself is plain, testable Python:

- `taptr.apps.demo.settings`: the limits and server defaults (light, read by the CLI parser);
- `taptr.apps.demo.uploads`: reading uploaded videos and bundled samples, clicked points,
  painted masks, and turning them into (t, x, y) queries;
- `taptr.apps.demo.handlers`: the two jobs the page runs (tracking, editing), each a plain
  function of the predictor API that writes its outputs into a fresh folder;
- `taptr.apps.demo.app`: the Gradio page, a thin layer that wires components to the handlers;
- `taptr.apps.demo.launch`: the private temporary workspace and the server's lifetime.

Only `app` imports Gradio, so ``import taptr`` and ``taptr --help`` never do. The demo uses
the API layer only (`taptr.api`, `taptr.viz`, `taptr.apps.editing`, `taptr.data.sample_video`).
"""
