"""Prints the size of every artifact of a scene (per file, image directories summed) with each stage's wall and CPU
seconds from its manifest, and what the lossy frames cost: PSNR of frames/ and conditions rgb/ to their exact images.

    python bench/bench_artifact_size.py SCENE [--json OUT.json]     # an existing scene (e.g. after `runner.py demo`)
    python bench/bench_artifact_size.py --demo DIR [--json OUT.json]  # runs `runner.py demo DIR` first (a few minutes)

The MCAP's frames (/camera/rgb: H.264 or JPEG) are decoded (H.264 by imageio-ffmpeg's ffmpeg program) and their PSNR
to the stored frames printed.

With --reference SCENE2 the table gets a second column (e.g. the same scene run with
`--set video.frame_format=png --set conditions.rgb_format=png`), the PSNR of SCENE's video frames and condition
RGB to SCENE2's, and the gaussians' fit figures of both.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

REPO = Path(__file__).resolve().parent.parent
MB = 1e6


def entry_sizes(artifacts: Path) -> dict[str, int]:
    """{'kind/file' or 'kind/dir/': bytes} of every artifact directory's entries (logs/ and manifests skipped)."""
    out: dict[str, int] = {}
    for kind in sorted(p for p in artifacts.iterdir() if p.is_dir() and p.name != "logs"):
        for e in sorted(kind.iterdir()):
            if e.name == "manifest.json":
                continue
            if e.is_dir():
                out[f"{kind.name}/{e.name}/"] = sum(f.stat().st_size for f in e.rglob("*") if f.is_file())
            else:
                out[f"{kind.name}/{e.name}"] = e.stat().st_size
    return out


def stage_times(artifacts: Path) -> dict[str, dict]:
    out = {}
    for m in sorted(artifacts.glob("*/manifest.json")):
        doc = json.loads(m.read_text())
        out[m.parent.name] = {"wall_s": round(float(doc.get("wall_s") or 0), 2), "cpu_s": round(float(doc.get("cpu_s") or 0), 2),
                              "peak_rss_mb": round(float(doc.get("peak_rss_mb") or 0))}
    return out


def image_psnr(a_files: list[Path], b_files: list[Path]) -> float:
    """PSNR (dB) of all of a_files' pixels to b_files' (the same frames in another format)."""
    import numpy as np

    from panoworld.io.rgb_image import decode_rgb

    se = n = 0.0
    for a, b in zip(a_files, b_files, strict=True):
        x = decode_rgb(a.read_bytes(), what=str(a)).astype(np.float64)
        y = decode_rgb(b.read_bytes(), what=str(b)).astype(np.float64)
        se += float(((x - y) ** 2).sum())
        n += x.size
    mse = se / max(n, 1)
    return float("inf") if mse == 0 else float(10 * np.log10(255.0**2 / mse))


def fidelity(scene: Path, ref: Path) -> dict:
    from panoworld.io.conditions import load_conditions
    from panoworld.io.video import read_video_doc

    out = {}
    va, vb = read_video_doc(scene / "artifacts" / "video"), read_video_doc(ref / "artifacts" / "video")
    out["video_frames_psnr_db"] = round(image_psnr(va.rgb, vb.rgb), 2)
    ca, cb = load_conditions(scene / "artifacts" / "conditions"), load_conditions(ref / "artifacts" / "conditions")
    out["conditions_rgb_psnr_db"] = round(image_psnr([ca.root / p for p in ca.rgb.paths],
                                                     [cb.root / p for p in cb.rgb.paths]), 2)
    for name, s in (("scene", scene), ("reference", ref)):
        info = json.loads((s / "artifacts" / "gaussians" / "manifest.json").read_text())["info"]
        out[f"{name}_gaussians"] = {"num_gaussians": info["num_gaussians"], "context_psnr": round(info["context_psnr"], 3),
                                    "context_ssim": round(info["eval"][0]["ssim"], 4) if info["eval"] else None}
    return out


def mcap_psnr(scene: Path) -> dict | None:
    """{'format', 'psnr_db'}: the MCAP's /camera/rgb frames decoded, their PSNR to video/frames/ (None: no MCAP)."""
    import imageio_ffmpeg
    import numpy as np

    from panoworld.io.rgb_image import decode_rgb
    from panoworld.io.video import read_video_doc
    from panoworld.io.video_mcap import MCAP_FILE, TOPIC_RGB, read_mcap

    doc = read_video_doc(scene / "artifacts" / "video")
    path = doc.root / MCAP_FILE
    if not path.is_file():
        return None
    msgs = read_mcap(path)[TOPIC_RGB]
    fmt = msgs[0].format
    if fmt == "h264":
        out = subprocess.run([imageio_ffmpeg.get_ffmpeg_exe(), "-loglevel", "error", "-f", "h264", "-i", "-", "-f",
                              "rawvideo", "-pix_fmt", "rgb24", "-"], input=b"".join(m.data for m in msgs),
                             capture_output=True, check=True).stdout
        frames = np.frombuffer(out, np.uint8).reshape(-1, doc.height, doc.width, 3)
    else:
        frames = [decode_rgb(m.data) for m in msgs]
    se = n = 0.0
    for f, p in zip(frames, doc.rgb, strict=True):
        d = f.astype(np.float64) - decode_rgb(p.read_bytes(), what=str(p))
        se += float((d**2).sum())
        n += d.size
    return {"format": fmt, "frames": len(msgs), "psnr_db": round(float(10 * np.log10(255.0**2 / (se / n))), 2)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("scene", nargs="?", type=Path, help="a scene directory with artifacts/")
    ap.add_argument("--demo", type=Path, help="run `runner.py demo DIR` first and measure DIR/scene")
    ap.add_argument("--reference", type=Path, help="a second scene to compare with (its sizes, and image PSNR)")
    ap.add_argument("--json", type=Path, help="also write the figures as JSON here")
    a = ap.parse_args()
    if a.demo is not None:
        subprocess.run([sys.executable, "runner.py", "demo", str(a.demo)], cwd=REPO, check=True)
        a.scene = a.demo / "scene"
    if a.scene is None or not (a.scene / "artifacts").is_dir():
        print(f"{a.scene}: no artifacts/ here; pass a scene directory or --demo DIR", file=sys.stderr)
        return 2
    sizes = entry_sizes(a.scene / "artifacts")
    ref = entry_sizes(a.reference / "artifacts") if a.reference else None
    names = sorted(set(sizes) | set(ref or {}))
    w = max(len(n) for n in names)
    head = f"{'artifact entry':<{w}}  {'MB':>8}" + (f"  {'reference MB':>12}" if ref is not None else "")
    print(head)
    print("-" * len(head))
    for n in names:
        line = f"{n:<{w}}  {sizes.get(n, 0) / MB:>8.2f}"
        if ref is not None:
            line += f"  {ref.get(n, 0) / MB:>12.2f}"
        print(line)
    total = sum(sizes.values())
    print(f"{'total':<{w}}  {total / MB:>8.2f}" + (f"  {sum(ref.values()) / MB:>12.2f}" if ref is not None else ""))
    times = stage_times(a.scene / "artifacts")
    print(f"\n{'stage':<12} {'wall s':>8} {'CPU s':>8} {'peak MB':>8}")
    for k, t in times.items():
        print(f"{k:<12} {t['wall_s']:>8.2f} {t['cpu_s']:>8.2f} {t['peak_rss_mb']:>8}")
    out = {"scene": str(a.scene), "sizes_bytes": sizes, "total_bytes": total, "stages": times,
           "mcap_rgb": mcap_psnr(a.scene)}
    if out["mcap_rgb"] is not None:
        m = out["mcap_rgb"]
        print(f"\nvideo.mcap /camera/rgb: {m['frames']} frames as {m['format']}, {m['psnr_db']} dB PSNR to video/frames/")
    if a.reference is not None:
        out.update(reference=str(a.reference), reference_sizes_bytes=ref, reference_total_bytes=sum(ref.values()),
                   reference_stages=stage_times(a.reference / "artifacts"), fidelity=fidelity(a.scene, a.reference))
        print("\n" + json.dumps(out["fidelity"], indent=1))
    if a.json:
        a.json.write_text(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
