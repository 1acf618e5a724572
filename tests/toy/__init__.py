"""Toy stages and pipeline used to test the runner's DAG, cache and crash behaviour."""
