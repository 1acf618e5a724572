"""Pipeline stages: one module per stage, each with NAME, VERSION, ARTIFACT, INPUTS, Params, run() and main()."""

import os
import sys

# A stage process (`python -m stages.NAME`) loads this package before numpy loads OpenBLAS: one BLAS thread there.
# OpenBLAS's threads busy-wait between calls and numpy's products in the stages are thin ((M, 3) @ (3, 3)), so on a
# 2-core machine shared with other stages they cost CPU they do not save (docs/multi.md, "Speed"). The depth stage
# keeps them: the last bits of its outputs depend on the thread count. A value already set wins.
_argv = sys.orig_argv
_stage = _argv[_argv.index("-m") + 1] if "-m" in _argv[:-1] else ""
if _stage.startswith("stages.") and _stage != "stages.depth":
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
