"""The capture rig at the nadir: detection (heuristic and learned), shadow, removal."""
