"""Training data precomputed from datasets: conditions per clip."""
