"""Prints how long `runner.py` takes to refuse each hostile input of issue #48 (wall seconds of the whole command, and
of the runner's scene checks alone), with its exit code and line: every refusal should take well under 2 s whatever
the file's size (an 80 GB sparse depth, a 1 KB YAML alias bomb).

  python bench/bench_refusals.py [--json]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import cv2
import numpy as np


def _home(d: Path) -> Path:
    (d / "panoramas").mkdir(parents=True)
    (d / "depths").mkdir()
    for i, n in enumerate("abc"):
        cv2.imwrite(str(d / "panoramas" / f"{n}.png"), np.full((32, 64, 3), 40 * i, np.uint8))
        np.save(d / "depths" / f"{n}.npy", np.full((32, 64), 2.0, np.float32))
    return d


def _single(d: Path) -> Path:
    d.mkdir(parents=True)
    cv2.imwrite(str(d / "panorama.png"), np.full((16, 32, 3), 90, np.uint8))
    return d


def _sparse_npy(path: Path, shape=(100_000, 200_000)) -> None:
    with open(path, "wb") as f:
        np.lib.format.write_array_header_1_0(f, {"descr": "<f4", "fortran_order": False, "shape": shape})
        f.truncate(f.tell() + int(np.prod(shape)) * 4)


def _alias_bomb(levels: int = 9) -> str:
    text, prev = "a: &a [x, x, x, x, x, x, x, x, x]\n", "a"
    for i in range(1, levels):
        text += f"l{i}: &l{i} [{', '.join(['*' + prev] * 9)}]\n"
        prev = f"l{i}"
    return text


def _png_bomb(path: Path, w: int, h: int) -> None:
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
                     + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b""))


def cases(root: Path) -> dict[str, tuple[Path, list[str]]]:
    """{case: (scene, runner args)}."""
    out = {}
    d = _home(root / "home_sparse_depth")
    _sparse_npy(d / "depths" / "b.npy")
    out["home: 80 GB sparse depths/b.npy"] = (d, ["run", str(d)])
    d = _single(root / "single_sparse_depth")
    _sparse_npy(d / "depth.npy")
    out["one panorama: 80 GB sparse depth.npy"] = (d, ["run", str(d)])
    d = _single(root / "alias_bomb")
    (d / "scene.yaml").write_text(_alias_bomb())
    out["scene.yaml: 9-level alias bomb (status)"] = (d, ["status", str(d)])
    d = _home(root / "unsafe_name")
    os.rename(d / "panoramas" / "c.png", d / "panoramas" / "...png")
    out["home: panoramas/...png"] = (d, ["run", str(d)])
    d = _home(root / "poses_far")
    T = np.eye(4)
    T[0, 3] = 1e12
    (d / "poses.json").write_text(json.dumps({"a": np.eye(4).tolist(), "b": T.tolist()}))
    out["home: poses.json 1e12 m"] = (d, ["run", str(d)])
    d = _home(root / "poses_deep")
    (d / "poses.json").write_text('{"a": ' + "[" * 100_000 + "]" * 100_000 + "}")
    out["home: poses.json nested 100 000 deep"] = (d, ["run", str(d)])
    d = _home(root / "mask_bomb")
    (d / "rig_masks").mkdir()
    _png_bomb(d / "rig_masks" / "a.png", 30000, 15000)
    out["home: rig_masks/a.png 30000x15000"] = (d, ["run", str(d)])
    d = _single(root / "report_fifo")
    os.mkfifo(root / "fifo")
    out["report --out FIFO"] = (d, ["report", str(d), "--out", str(root / "fifo")])
    d = _single(root / "view_port")
    (d / "artifacts").mkdir()
    out["view --port 99999"] = (d, ["view", str(d), "--port", "99999"])
    out["view --host no.such.host.invalid"] = (d, ["view", str(d), "--host", "no.such.host.invalid"])
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--json", action="store_true", help="print the rows as JSON")
    args = ap.parse_args(argv)
    from panoworld.core.errors import PanoWorldError
    from panoworld.framework import pipeline as pl

    pipe = pl.Pipeline.load()
    rows = []
    with tempfile.TemporaryDirectory(prefix="bench_refusals_") as tmp:
        for name, (scene, cmd) in cases(Path(tmp)).items():
            t0 = time.perf_counter()
            proc = subprocess.run([sys.executable, str(REPO / "runner.py"), *cmd], capture_output=True, text=True,
                                  cwd=REPO, timeout=120)
            wall = time.perf_counter() - t0
            checks = None
            if cmd[0] in ("run", "status"):
                t0 = time.perf_counter()
                try:
                    pl.open_scene(scene, pipe)
                except PanoWorldError:
                    pass
                checks = time.perf_counter() - t0
            lines = proc.stderr.strip().splitlines()
            rows.append({"case": name, "exit": proc.returncode, "command_s": round(wall, 3),
                         "checks_s": None if checks is None else round(checks, 4), "stderr_lines": len(lines),
                         "line": (lines[-1] if lines else "")[:110]})
    if args.json:
        print(json.dumps(rows, indent=1))
        return 0
    print(f"{'case':<42} {'exit':>4} {'command s':>9} {'checks s':>8}  line")
    for r in rows:
        checks = f"{r['checks_s']:.3f}" if r["checks_s"] is not None else "-"
        print(f"{r['case']:<42} {r['exit']:>4} {r['command_s']:>9.2f} {checks:>8}  {r['line']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
