"""Programs built on the framework: batch runs, evaluation, precompute, reports, training, the viewer, synthetic scenes."""
