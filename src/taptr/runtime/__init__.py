"""How the networks run on a given machine: the machinery around `taptr.model`.

`taptr.model` holds the three networks (TAPTR v1, TAPTRv2, TAPTRv3): modules that compute.
This package holds what decides how they run here. `runner` is the one object the
predictor and its streams run through: device, precision (`precision`, `denormals`), the
speed choices timed once per machine and shape and remembered on disk (`measured`,
`measured_file`, `kernel_choice`, `cpu_choice`, `encode_choice`), TAPTRv3's per-frame step
captured and replayed where that pays (`step_capture`, `capture_timing`, `capture_buckets`),
the loop of each model family (`engines`: `window_engine`, `frame_engine`) and the frame
caches (`frames`). `op_count` counts what a frame dispatches. It imports the networks;
they never import it.
"""
