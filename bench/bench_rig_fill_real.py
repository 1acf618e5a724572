"""The rig's fill against real floors: each labelled rig's shape moved onto its own panorama's seen floor, filled,
scored against the floor that was there.

    python bench/bench_rig_fill_real.py [--split dev|test|all] [--json F] [--save DIR]

The rig removal cannot be scored against the floor under a real tripod (nobody saw it), but the same hole can be cut
anywhere else on the floor the panorama shows. Per labelled panorama (bench_rig_real: ZInD east, west, garage; at
the depth stage's working size and default settings): on the downward face, the label's mask moved in 8 directions
by 0.8 to 2 times its extent, the first place per direction where it lies on the floor the detection lets the fill
copy from (`det.source`, >= 97 %), clear of the label, the detected mask and its shadow grown by 4 pixels, with >= 70
% of the floor ring around it such floor. Each site is filled by the two fills `remove_rig` chooses between, from the
floor around the hole alone (the label, the rig and its shadow left out of their source):

- ring: `ring_fill` (what a solid base gets: the floor ring just outside the hole, its light carried across);
- plane: `inpaint_plane` (what thin legs get: floor texture from anywhere on the face, lattice or patches).

Scores over the hole's pixels against the floor that was there: `low` the RMS error (sRGB levels) of the
low frequencies (both images blurred by a Gaussian of 4 pixels: the light and the floor's large pattern, what a
viewer sees from afar), `lum` the fill's mean brightness (RGB mean) over the truth's, and PSNR (which favours a blur over a
texture of the right contrast: a copied texture's detail is independent of the truth's, doubling that part of the
error). Dev = east + garage, test = west, as bench_rig_real.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import bench_rig_real as rr
import cv2
import numpy as np

DIRECTIONS = 8
DISTANCES = (0.8, 1.0, 1.2, 1.4, 1.7, 2.0)
MIN_ON_SOURCE = 0.97
MIN_RING_SOURCE = 0.7
CLEAR_PX = 4
LOW_SIGMA_PX = 4.0


def sites(label: np.ndarray, keep_out: np.ndarray, source: np.ndarray, ring_px: float) -> list[np.ndarray]:
    """Holes (S, S) bool: label moved per direction to the first distance (times its extent) where it lies on source
    (>= MIN_ON_SOURCE), clear of keep_out, and its ring of ring_px is mostly source clear of keep_out
    (MIN_RING_SOURCE)."""
    floor = source & ~keep_out
    S = label.shape[0]
    ys, xs = np.nonzero(label)
    h, w = int(np.ptp(ys)) + 1, int(np.ptp(xs)) + 1
    grow = np.ones((2 * int(ring_px) + 1,) * 2, np.uint8)
    out = []
    for ang in np.arange(DIRECTIONS) * 2 * np.pi / DIRECTIONS:
        for dist in DISTANCES:
            dy, dx = int(round(np.sin(ang) * dist * h)), int(round(np.cos(ang) * dist * w))
            if not (0 <= ys.min() + dy and ys.max() + dy < S and 0 <= xs.min() + dx and xs.max() + dx < S):
                continue
            hole = np.zeros_like(label)
            hole[ys + dy, xs + dx] = True
            ring = (cv2.dilate(hole.astype(np.uint8), grow) > 0) & ~hole
            if (hole & keep_out).any() or source[hole].mean() < MIN_ON_SOURCE:
                continue
            if floor[ring].mean() < MIN_RING_SOURCE:
                continue
            out.append(hole)
            break
    return out


def scores(fill: np.ndarray, truth: np.ndarray, hole: np.ndarray) -> dict:
    """low-frequency RMS (levels), mean brightness ratio and PSNR of fill against truth (S, S, 3) float over hole."""
    lo = cv2.GaussianBlur(fill, (0, 0), LOW_SIGMA_PX) - cv2.GaussianBlur(truth, (0, 0), LOW_SIGMA_PX)
    mse = float(((fill[hole] - truth[hole]) ** 2).mean())
    return {"low": float(np.sqrt((lo[hole] ** 2).mean())), "lum": float(fill[hole].mean() / truth[hole].mean()),
            "psnr": float(10 * np.log10(255.0**2 / max(mse, 1e-9)))}


def fill_rows(split: str, save: Path | None) -> list[dict]:
    from panoworld.depth.rig.face import erp_mask_to_face, nadir_view
    from panoworld.depth.rig.inpaint import RING_WIDTH_DEG, inpaint_plane, ring_fill
    from panoworld.geometry.cube_views import render_view

    doc = json.loads(rr.LABELS.read_text())
    rows = []
    for name, pano, depth in rr.rig_panoramas():
        part = rr.SPLIT[name.split("/")[0]]
        if split != "all" and part != split:
            continue
        rgb, res, params = rr.stage_input(pano, depth)
        c, _ = rr.clean(rgb, res, params, depth)
        det = c.rig
        H, W = rgb.shape[:2]
        view = nadir_view(H)
        face = render_view(rgb, view).astype(np.float32)
        label = erp_mask_to_face(rr.label_mask(doc["labels"][name], doc["view"], H, W), view)
        rig = label.copy()
        for m in (det.mask, det.shadow):
            if m is not None:
                rig |= erp_mask_to_face(m, view)
        keep_out = cv2.dilate(rig.astype(np.uint8), np.ones((2 * CLEAR_PX + 1,) * 2, np.uint8)) > 0
        source = det.source if det.source is not None else np.ones_like(label)
        width = view.focal * np.deg2rad(RING_WIDTH_DEG)
        found = sites(label, keep_out, source, width)
        floor = source & ~keep_out
        per = []
        for k, hole in enumerate(found):
            ring = ring_fill(face, hole, floor, width)
            plane = inpaint_plane(face, hole, floor)
            per.append({"ring": scores(ring, face, hole), "plane": scores(plane, face, hole)})
            if save is not None:
                save.mkdir(parents=True, exist_ok=True)
                ys, xs = np.nonzero(hole)
                sl = (slice(max(ys.min() - 40, 0), ys.max() + 40), slice(max(xs.min() - 40, 0), xs.max() + 40))
                shown = face.copy()
                cnt, _ = cv2.findContours(hole.astype(np.uint8), cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
                cv2.drawContours(shown, cnt, -1, (0, 255, 0), 1)
                pic = np.concatenate([shown[sl], ring[sl], plane[sl]], 1)
                cv2.imwrite(str(save / f"{name.replace('/', '_')}_{k}.png"),
                            cv2.cvtColor(np.clip(pic, 0, 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
        row = {"panorama": name, "split": part, "sites": len(per)}
        for fill in ("ring", "plane"):
            for key in ("low", "lum", "psnr"):
                row[f"{fill}_{key}"] = float(np.mean([p[fill][key] for p in per])) if per else None
        rows.append(row)
        print(f"  {name}: {len(per)} sites", flush=True)
    return rows


def table(rows: list[dict]) -> str:
    def f(v, spec):
        return "-" if v is None else format(v, spec)

    lines = ["| panorama | split | sites | ring: low | plane: low | ring: brightness | plane: brightness | ring: PSNR | plane: PSNR |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['panorama']} | {r['split']} | {r['sites']} | {f(r['ring_low'], '.1f')} | "
                     f"{f(r['plane_low'], '.1f')} | {f(r['ring_lum'], '.3f')} | {f(r['plane_lum'], '.3f')} | "
                     f"{f(r['ring_psnr'], '.2f')} | {f(r['plane_psnr'], '.2f')} |")
    for part in ("dev", "test"):
        sub = [r for r in rows if r["split"] == part and r["sites"]]
        if not sub:
            continue

        def mean(key, spec, sub=sub):
            return format(float(np.mean([r[key] for r in sub])), spec)

        def off(key, sub=sub):
            return format(float(np.mean([abs(1 - r[key]) for r in sub])), ".1%")

        lower = sum(r["ring_low"] < r["plane_low"] for r in sub)
        lines.append(f"| **{part}** ({len(sub)} with sites) | | {sum(r['sites'] for r in sub)} | "
                     f"{mean('ring_low', '.1f')} (lower on {lower}) | {mean('plane_low', '.1f')} | "
                     f"{off('ring_lum')} off | {off('plane_lum')} off | {mean('ring_psnr', '.2f')} | "
                     f"{mean('plane_psnr', '.2f')} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = rr.labelled_parser(__doc__, "folder for each site: the hole, the ring fill, the plane fill").parse_args(argv)
    if not rr.have_data():
        return 2
    rows = fill_rows(args.split, args.save)
    print(table(rows))
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
