"""The ``taptr`` command line."""
