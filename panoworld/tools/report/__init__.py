"""Self-contained HTML reports of a scene's artifacts and of precompute datasets (`runner.py report`)."""
