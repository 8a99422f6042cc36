"""Batch jobs: synthesis, training, evaluation, offline segmentation, experiments, benches and
the demo."""
