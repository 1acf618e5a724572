"""One runner per scene: the flock on its artifacts folder."""

from __future__ import annotations

import contextlib
import fcntl
import os
import time

from panoworld.core.errors import PipelineError
from panoworld.framework.execute import PARAMS_FILE_PREFIX
from panoworld.framework.scene import Scene
from panoworld.io import manifest as art
from panoworld.io.safe_write import write_text_atomic


class SceneLock:
    """One runner per scene: an exclusive, non-blocking flock on the artifacts directory itself (deleting a file
    cannot defeat it; stages re-check it and its inode before they commit), with the holder named in
    artifacts/.lock for the message a second runner gets. It dies with the process."""

    def __init__(self, scene: Scene):
        self.path = scene.artifacts / art.LOCK_FILE
        self.fd: int | None = None
        self.inode = ""

    def __enter__(self) -> SceneLock:
        arts = self.path.parent
        arts.mkdir(parents=True, exist_ok=True)
        fd = os.open(arts, os.O_RDONLY | os.O_DIRECTORY)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            try:
                holder = self.path.read_text(errors="replace")[:200].strip()
            except OSError:
                holder = ""
            raise PipelineError(
                f"{arts.parent}: another runner is working on this scene ({holder or 'unknown holder'}); "
                "wait for it to finish"
            ) from None
        self.fd = fd
        st = os.fstat(fd)
        self.inode = f"{st.st_dev}:{st.st_ino}"
        with contextlib.suppress(OSError):  # a read-only scene whose stages are all up to date still reports them
            write_text_atomic(self.path, f"pid {os.getpid()} since {time.strftime('%Y-%m-%d %H:%M:%S')}",
                              durable=False)  # the flock is the lock; this only names its holder
            for leftover in arts.glob(f"**/logs/{PARAMS_FILE_PREFIX}*.json"):  # of a killed runner
                leftover.unlink(missing_ok=True)
            art.sweep_leftovers(arts)
        return self

    def remove_bookkeeping(self) -> None:
        """While held: delete the lock file and the empty directories under artifacts/ (logs/ of refused stages)."""
        self.path.unlink(missing_ok=True)
        for d in sorted((p for p in self.path.parent.rglob("*") if p.is_dir()), key=lambda p: -len(p.parts)):
            with contextlib.suppress(OSError):
                d.rmdir()
        with contextlib.suppress(OSError):
            self.path.parent.rmdir()

    def __exit__(self, *exc) -> None:
        if self.fd is not None:
            fcntl.flock(self.fd, fcntl.LOCK_UN)
            os.close(self.fd)
            self.fd = None

