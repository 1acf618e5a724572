"""Pipeline stages: one module per stage, each with NAME, VERSION, ARTIFACT, INPUTS, Params, run() and main()."""

import os
import sys

# A stage runs as `python -m stages.NAME`: this package loads first, before numpy loads OpenBLAS. One BLAS thread:
# OpenBLAS's threads busy-wait between calls and numpy's products here are thin ((M, 3) @ (3, 3)), so on a 2-core
# machine shared with other stages its threads cost CPU they do not save (docs/multi.md, "Speed"). The depth stage
# keeps them: the last bits of its outputs depend on the thread count. A value already set wins.
if "stages.depth" not in sys.orig_argv:
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
