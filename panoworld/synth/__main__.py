"""`python -m panoworld.synth ...` entry point (same as `runner.py synth ...`)."""

import sys

from panoworld.synth.cli import main

sys.exit(main())
