"""Training: shared infrastructure (common), the video generator (video) and reconstruction (recon)."""
