"""Core types every layer uses: errors, shape checks, input limits, params, conventions, rotations, the backend registry."""
