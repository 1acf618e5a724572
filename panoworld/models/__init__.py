"""Learned models, each loaded from a local weights directory."""
