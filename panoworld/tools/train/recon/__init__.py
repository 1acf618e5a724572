"""Training of the reconstruction model: PanoVGGT camera + depth heads (stage 1) and its Gaussian head (stage 2)."""
