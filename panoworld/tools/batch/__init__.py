"""Whole datasets through the pipeline: scene discovery, sweep variants of the DAG's tail, local or Ray stage executors."""
