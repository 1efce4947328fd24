"""What a tracker does, written once in numpy: the rules every engine runs behind.

A TAPTR tracker is more than its networks: pixel queries and their checks, the support
points that surround them, each query returned on its own frame, the time-reversed pass
fused at the query frames, the frames resized to the model's input, and the records a
stream hands back. Those rules live here without torch, and every way of running the
networks takes them from here: `taptr.api` (PyTorch, eager or captured), `taptr.onnx`
(the exported graphs in onnxruntime or OpenVINO) and the official evaluation protocol
(`taptr.eval.official_protocol`).

- `support_schemes`: the registry of support schemes (count, points, parents, what
  points added mid-stream bring, the fallback past a budget);
- `stream_points`: a stream's user points, their identifiers and the support each brings;
- `pixel_queries`: (t, x, y) pixel queries checked, normalised, and put back on their
  own frames;
- `both_ways`: a forward pass and a time-reversed one, fused at each query frame;
- `resizing`: frames to the model's input size, the two ways a config can ask for;
- `results`: the records handed back (`TrackArrays`, `StreamUpdate`, `FrameCountError`).

Nothing here imports torch (tests/test_rooms.py imports every module in a process where
torch cannot be imported).
"""
