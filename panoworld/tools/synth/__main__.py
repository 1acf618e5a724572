"""`python -m panoworld.tools.synth ...` entry point (same as `runner.py synth ...`)."""

import sys

from panoworld.tools.synth.cli import main

sys.exit(main())
