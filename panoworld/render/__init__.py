"""Rendering: Gaussian splats (pinhole and ERP), mesh rasterisation, warped frames, image metrics."""
