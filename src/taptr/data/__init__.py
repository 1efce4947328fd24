"""Datasets: readers of TAP-Vid and Kubric files, synthetic videos, augmentation, sampling."""
