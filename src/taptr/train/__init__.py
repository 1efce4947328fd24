"""Training: the configuration, losses, optimiser recipe, EMA, DDP helpers and the loop.

Entry points are `taptr.train.loop.train` and the ``taptr train`` command.
"""
