"""Interactive 3D viewer of a scene (viser): `runner.py view`."""
