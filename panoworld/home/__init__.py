"""A home from several panoramas through the pipeline: the per-panorama depth layout, capture points, trajectories over the home and multi-source Gaussians."""
