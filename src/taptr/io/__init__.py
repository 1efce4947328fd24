"""Reading and writing files safely: videos, track files, atomic writes, bounded readers.

Everything here sits below the model: it knows frames, arrays and bytes, never networks.
Every reader checks what a file declares against `taptr.io.limits` before allocating.
"""
