"""Where weights come from, and why they are trusted.

- `registry`: model names, the released checkpoints they stand for, the default model and
  its bundled fallback (``taptr-small-synthetic.pth``, this folder's data), and
  `registry.load_model` / `registry.from_pretrained`, which turn a name or a file into a
  model;
- `hub`: weights published on the Hugging Face Hub (the local cache first);
- `drive`: TAPTRv3's weights on Google Drive (the weights folder first), fetched by
  `drive_download` through gdown;
- `transfer`: bounds on every download (first answer, least rate, size);
- `checkpoint`: reading and writing checkpoint files strictly and safely; `safe_checks`: checks
  of a file's content that cannot themselves be attacked; `identity`: named weights held to
  the architecture their name promises.

Nothing here downloads at import, and importing the package loads no torch.
"""
