"""How the networks run on a given machine: the machinery around `taptr.model`.

`taptr.model` holds the three networks (TAPTR v1, TAPTRv2, TAPTRv3): modules that compute.
This package holds what decides how they run here: which loop drives a model
(`drivers`), how frames are encoded and kept (`frames`), the choices timed once per
machine and shape and remembered on disk (`measured`, `measured_file`, `kernel_choice`,
`cpu_choice`, `encode_choice`), TAPTRv3's per-frame step captured and replayed where that
pays (`step_capture`), and what a frame costs in dispatched operations (`op_count`). It
imports the networks; they never import it.
"""
