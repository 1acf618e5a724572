"""Weights by name: the registry of every learned backend's weights, offline resolution of `hf:` ids, and fetching."""
