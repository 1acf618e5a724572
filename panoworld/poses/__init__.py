"""The poses stage: per-frame poses of the video (COLMAP SfM, the plan, PanoVGGT) and their exports."""
