"""Niantic SPZ files of Gaussians (the compact format web viewers open), written and read with gsply."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from panoworld.io.gaussian_set import Gaussians
from panoworld.io.splat_ply import REST_PER_DEGREE, used_sh_degree


def write_gaussians_spz(path: str | Path, gaussians: Gaussians) -> None:
    """SPZ version 3 (gzip, smallest-three quaternions, 12 fractional bits: 0.24 mm positions) with the SH degree the
    Gaussians use, in the same frame as gaussians.ply (canonical: metres, OpenCV axes, y down), as SPZ converters from
    INRIA .ply files store it."""
    import gsply

    g = gaussians.numpy()
    k = REST_PER_DEGREE[used_sh_degree(g.sh_rest)]
    quats = np.asarray(g.quats, np.float32)
    quats = quats / np.maximum(np.linalg.norm(quats, axis=1, keepdims=True), 1e-12)
    p = np.clip(np.asarray(g.opacities, np.float64), 1e-7, 1 - 1e-7)
    data = gsply.GSData(
        means=np.ascontiguousarray(g.means, np.float32),
        scales=np.log(np.maximum(np.asarray(g.scales, np.float32), 1e-12)),
        quats=np.ascontiguousarray(quats),
        opacities=np.log(p / (1 - p)).astype(np.float32),
        sh0=np.ascontiguousarray(g.sh_dc, np.float32),
        shN=np.ascontiguousarray(g.sh_rest[:, :k], np.float32),
    )
    gsply.write_spz(str(path), data)
    _zero_gzip_mtime(Path(path))


def _zero_gzip_mtime(path: Path) -> None:
    """Zero the gzip header's modification time (bytes 4-7; no header CRC covers them), so that the same Gaussians give
    the same file bytes."""
    with open(path, "r+b") as f:
        head = f.read(10)
        if len(head) == 10 and head[:3] == b"\x1f\x8b\x08" and not head[3] & 0x02:
            f.seek(4)
            f.write(b"\x00\x00\x00\x00")


def read_gaussians_spz(path: str | Path) -> Gaussians:
    """An SPZ file (versions 1-4) as Gaussians; ValueError naming the file when it is not one."""
    import gsply

    try:
        d = gsply.read_spz(str(path))
    except (OSError, ValueError, EOFError) as e:
        raise ValueError(f"{path}: not a readable .spz file ({e})") from None
    n = len(d.means)
    rest = np.zeros((n, 0, 3), np.float32) if d.shN is None else np.asarray(d.shN, np.float32).reshape(n, -1, 3)
    return Gaussians(
        means=np.asarray(d.means, np.float32),
        scales=np.exp(np.asarray(d.scales, np.float32)),
        quats=np.asarray(d.quats, np.float32),
        opacities=(1.0 / (1.0 + np.exp(-np.asarray(d.opacities, np.float64)))).astype(np.float32),
        sh_dc=np.asarray(d.sh0, np.float32),
        sh_rest=rest,
    )
