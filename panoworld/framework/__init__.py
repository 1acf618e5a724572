"""The framework: the pipeline (DAG, params, cache, locking), the stage contract, code digests, weights hub."""
