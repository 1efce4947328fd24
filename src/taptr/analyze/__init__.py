"""Analyses of trained models (`taptr analyze ...`): what a model does, not how well it tracks."""
