"""The gaussians stage: voxel-aligned 3D Gaussians fused from the video, its kernels and its artifact."""
