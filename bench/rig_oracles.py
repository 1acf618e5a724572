"""The oracles of the rig bench (bench_rig.py): the true mask, the true light and the true fill against the detected
ones, and the split of a removal's error under the mask and in low frequencies."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from panoworld.depth.rig import nadir as rig_nadir
from panoworld.depth.rig import remove as rig_remove
from panoworld.depth.rig.remove import nadir_cap_psnr
from panoworld.tools.synth.rig import RigKind

LOW_DEG = 1.5
"""Gaussian sigma (degrees, on the downward face) that splits a fill's error into low frequencies (mean colour,
shading) and texture (grout, plank seams, veins)."""


def true_light(scene, kind, depth: np.ndarray) -> np.ndarray | None:
    """The generator's soft-shadow light factor (H, W) for tripod-shadow, None for the other cases."""
    from panoworld.tools.synth.rig import shadow_gain

    if kind != RigKind.TRIPOD_SHADOW:
        return None
    return shadow_gain(scene.world_from_canonical, scene.tracks[0].camera_height, depth)


def true_rig(scene, kind, rgb: np.ndarray, depth: np.ndarray, clean: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(the rig's own ERP pixels with its cast shadows from the room's lights, true_light): what a perfect detector
    would return, the soft shadow of tripod-shadow divided out."""
    light = true_light(scene, kind, depth)
    img = rgb.astype(np.float64)
    if light is not None:
        img = 255.0 * np.clip((img / 255.0) ** 2.2 / light[..., None], 0, 1) ** (1 / 2.2)
    nearer = np.isfinite(depth) & (depth < scene.render(scene.world_from_canonical, *depth.shape)[1] - 1e-3)
    return (np.abs(img - clean).max(-1) > 8.5) | nearer, light


def true_relight(scene, rgb: np.ndarray, depth: np.ndarray, light: np.ndarray | None, mask: np.ndarray):
    """(the nadir face, the face gain that divides out `light` (ones where None), the floor source outside the rig
    `mask` on the relit face, the ERP shadow mask outside `mask`): the relighting with the generator's true light."""
    from panoworld.depth.rig.face import erp_mask_to_face, face_to_erp_mask, nadir_view
    from panoworld.geometry.cube_views import render_view
    from panoworld.room.light import apply_gain

    H, W = rgb.shape[:2]
    view = nadir_view(H)
    gain = np.ones((view.size, view.size), np.float32)
    if light is not None:
        gain = 1.0 / np.maximum(render_view(light.astype(np.float32), view), 1e-3)
    nf = rig_nadir.nadir_face(rgb, depth, np.isfinite(depth) & (depth > 0), scene.tracks[0].camera_height)
    source = rig_nadir.floor_source(apply_gain(nf.face, gain), nf) & ~erp_mask_to_face(mask, view)
    return nf, gain, source, face_to_erp_mask(gain > 1.0, view, H, W) & ~mask


def oracle_detection(scene, kind, rgb: np.ndarray, depth: np.ndarray, clean: np.ndarray):
    """A RigDetection of the true rig mask (true_rig, grown by the detector's rim on the downward face) and, for
    tripod-shadow, the generator's light factor: remove_rig on it measures the fill alone."""
    from panoworld.depth.rig.face import erp_mask_to_face, face_to_erp_mask, nadir_view

    view = nadir_view(rgb.shape[0])
    mask, light = true_rig(scene, kind, rgb, depth, clean)
    mask |= face_to_erp_mask(rig_nadir.dilate_rim(erp_mask_to_face(mask, view), view), view, *rgb.shape[:2])
    _, gain, source, shadow = true_relight(scene, rgb, depth, light, mask)
    return rig_nadir.RigDetection(True, "oracle", "legs", mask, shadow, shadow_gain=None if light is None else gain,
                            source=source)


def mask_split(scene, kind, rgb: np.ndarray, depth: np.ndarray, clean: np.ndarray, det, out: np.ndarray) -> dict:
    """What the detected mask costs: the cap's error share on the true rig and its cast shadows (true_rig) left outside
    the detected mask (`missed_share`) and the cap with the same removal (the detected shadow and fill) on the true
    mask instead of the detected one (`psnr_true_mask`)."""
    from dataclasses import replace

    truth = true_rig(scene, kind, rgb, depth, clean)[0]
    m = det.mask if det.found else np.zeros_like(truth)
    shadow = det.shadow & ~truth if det.found else np.zeros_like(truth)
    return {"missed_share": error_split(out, clean, truth & ~m)["under_share"],
            "psnr_true_mask": nadir_cap_psnr(rig_remove.remove_rig(rgb, replace(det, found=True, mask=truth, shadow=shadow)), clean)}


LIGHT_BANDS_DEG = (0.0, 5.0, 10.0, 15.0, 20.0, 30.0)
"""Rings (degrees from the nadir) in which relight_oracle compares the detected light factor with the true one."""
SECTOR_BANDS_DEG = (5.0, 10.0, 15.0, 20.0, 24.0)
"""Rings (degrees from the nadir) in which relight_oracle reports the floor's light per azimuth sector."""


def relight_oracle(scene, kind, rgb: np.ndarray, depth: np.ndarray, clean: np.ndarray, det) -> dict:
    """What the relighting costs: the same removal (detected mask, usual fill) with the generator's true soft-shadow
    factor instead of the detected one (none for tripod: the floor is not relit), `psnr_true_light`; and per ring of
    LIGHT_BANDS_DEG on the floor outside the mask, the detected gain over the true one (`relight_<a>_<b>`, mean of
    the ratio - 1: > 0 the floor relit too bright, the profile too deep; < 0 too shallow); per ring of
    SECTOR_BANDS_DEG the floor's light over the floor-light model in 8 azimuth sectors, min-max, next to the radial
    profile's (`sectors_<a>_<b>`: a shadow around the rig dims every sector alike) and the true factor's."""
    from dataclasses import replace

    from panoworld.depth.rig.face import erp_mask_to_face, face_polar, nadir_view
    from panoworld.depth.rig.shadow import floor_light, sector_light

    view = nadir_view(rgb.shape[0])
    nf, gain, source, shadow = true_relight(scene, rgb, depth, true_light(scene, kind, depth), det.mask)
    fmask = erp_mask_to_face(det.mask, view)
    out = rig_remove.remove_rig(rgb, replace(det, shadow_gain=gain, shadow=shadow, source=source))
    row = {"psnr_true_light": nadir_cap_psnr(out, clean), "shadow_sectors": f"{det.stats.get('shadow_sectors', '-')}, "
           f"{det.stats.get('shadow_even_sectors', '-')}"}
    row.update(disc_relight(rgb, clean, det, nf, gain))
    det_gain = det.shadow_gain if det.shadow_gain is not None else np.ones_like(gain)
    theta, _ = face_polar(view)
    floor = nf.on_floor & ~fmask
    for a, b in zip(LIGHT_BANDS_DEG[:-1], LIGHT_BANDS_DEG[1:]):
        sel = floor & (theta >= a) & (theta < b)
        row[f"relight_{a:.0f}_{b:.0f}"] = float(np.mean(det_gain[sel] / gain[sel]) - 1.0) if sel.any() else None
    fit = floor_light(nf.face, fmask, nf.on_floor & rig_nadir.floor_chroma(nf.face, nf.ring_floor), theta, view.focal)
    if fit is not None:
        lit = sector_light(fit, theta, nf.phi, SECTOR_BANDS_DEG)
        for i, (a, b) in enumerate(zip(SECTOR_BANDS_DEG[:-1], SECTOR_BANDS_DEG[1:])):
            ring = (theta >= a) & (theta < b)
            prof = float(np.interp(0.5 * (a + b), fit.knots, fit.profile))
            row[f"sectors_{a:.0f}_{b:.0f}"] = (f"{np.nanmin(lit[i]):.2f}-{np.nanmax(lit[i]):.2f} "
                                               f"({prof:.2f}; {1 / np.median(gain[ring]):.2f})")
    return row


def disc_relight(rgb: np.ndarray, clean: np.ndarray, det, nf, true_gain: np.ndarray) -> dict:
    """The relighting's decision and its shadow model: the cap without any relighting (`psnr_no_relight`), and with
    the floor relit by rig_shadow.disc_shadow's soft disc instead of the radial profile where the removal relights
    (`psnr_disc_light`; unchanged where it does not), the disc's depth / radius / blur (deg) / gain of fit (`disc`)
    and its gain over the true one (true_gain, on the face) per ring of SECTOR_BANDS_DEG 5-20 outside the mask
    (`disc_over_true`, %)."""
    from dataclasses import replace

    from panoworld.depth.rig.face import erp_mask_to_face, face_to_erp_mask
    from panoworld.depth.rig.shadow import disc_shadow

    H, W = rgb.shape[:2]
    row = {"psnr_no_relight": nadir_cap_psnr(rig_remove.remove_rig(rgb, replace(det, shadow_gain=None, shadow=None)), clean)}
    fmask = rig_nadir.dilate_rim(erp_mask_to_face(det.mask, nf.view), nf.view)
    disc = disc_shadow(nf.face, fmask, nf.on_floor & rig_nadir.floor_chroma(nf.face, nf.ring_floor), nf.theta, nf.view.focal)
    if disc is None:
        return row
    deg = lambda x: float(np.rad2deg(np.arctan(x)))
    row["disc"] = f"{disc.depth:.2f} / {deg(disc.radius):.1f} / {deg(disc.blur):.1f} / {disc.gain_of_fit:.3f}"
    g, floor = disc.gain(nf.theta), nf.on_floor & ~fmask
    rings = [floor & (nf.theta >= a) & (nf.theta < b) for a, b in zip(SECTOR_BANDS_DEG[:-2], SECTOR_BANDS_DEG[1:-1])]
    row["disc_over_true"] = " / ".join(f"{100 * (np.mean(g[m] / true_gain[m]) - 1):+.0f}" for m in rings if m.any())
    row["psnr_disc_light"] = nadir_cap_psnr(rig_remove.remove_rig(rgb, det), clean)
    if det.shadow is not None and det.shadow.any():
        relit = replace(det, shadow_gain=g, shadow=face_to_erp_mask(g > 1.0, nf.view, H, W) & ~det.mask)
        row["psnr_disc_light"] = nadir_cap_psnr(rig_remove.remove_rig(rgb, relit), clean)
    return row


def fill_oracle(scene, kind, rgb: np.ndarray, depth: np.ndarray, clean: np.ndarray, det, pictures: Path,
                odet=None) -> dict:
    """The fill's ceiling and its error split: remove_rig on oracle_detection: `psnr_oracle`. On that fill, the cap
    cap on the downward face (`face_oracle`) with only its low-frequency error (LOW_DEG; texture perfect: `face_low`),
    with only its texture error (`face_tex`), the fill blurred (`face_smooth_fill`) and a texture-free guess that is
    the truth's own low-pass inside the mask (`face_smooth`).
    Pictures (truth | oracle fill | fill, the downward face) go to pictures/ when it is not Path()."""
    import cv2

    from panoworld.depth.rig.face import erp_mask_to_face, face_polar, nadir_view
    from panoworld.geometry.cube_views import render_view

    H, W = rgb.shape[:2]
    view = nadir_view(H)
    odet = odet or oracle_detection(scene, kind, rgb, depth, clean)
    mask = odet.mask
    out = rig_remove.remove_rig(rgb, odet)
    # The split on the downward face (a plane view: one blur scale everywhere), solid-angle weighted within 15 deg.
    sig = LOW_DEG * np.pi / 180 * view.focal
    theta, _ = face_polar(view)
    cap = (theta < 15.0)[..., None] * np.cos(np.deg2rad(theta))[..., None] ** 3
    f_out, f_clean = (render_view(a, view).astype(np.float32) for a in (out, clean))
    f_mask = erp_mask_to_face(mask, view)[..., None]
    low_err = cv2.GaussianBlur(f_out - f_clean, (0, 0), sig)
    clean_low = cv2.GaussianBlur(f_clean, (0, 0), sig)

    def face_psnr(img: np.ndarray) -> float:
        err = np.where(f_mask, img, f_out) - f_clean
        return 10 * np.log10(255.0**2 / max(float((cap * err**2).sum() / (3 * cap.sum())), 1e-12))

    row = {"psnr_oracle": nadir_cap_psnr(out, clean), "oracle_iou_det": float((mask & det.mask).sum() / max(
        (mask | det.mask).sum(), 1)) if det.found else 0.0, "face_oracle": face_psnr(f_out),
           "face_low": face_psnr(f_clean + low_err), "face_tex": face_psnr(f_out - low_err),
           "face_smooth": face_psnr(clean_low), "face_smooth_fill": face_psnr(cv2.GaussianBlur(f_out, (0, 0), sig))}
    if pictures != Path():
        pictures.mkdir(parents=True, exist_ok=True)
        pic = np.concatenate([render_view(clean, view), render_view(out, view),
                              render_view(rig_remove.remove_rig(rgb, det) if det.found else rgb, view)], 1)
        cv2.imwrite(str(pictures / f"{scene.meta['preset']}_{scene.meta['seed']}_{kind}_{H}.jpg"), pic[..., ::-1],
                    [cv2.IMWRITE_JPEG_QUALITY, 90])
    return row


def error_split(out: np.ndarray, clean: np.ndarray, mask: np.ndarray, deg: float = 15.0) -> dict:
    """Shares of the nadir cap's squared error (solid-angle weighted) under the removed mask (`under_share`; the
    rest is outside it: missed rig, shadow residue) and in its low frequencies (`lowfreq_share`: the error blurred
    by a 6 px Gaussian; the rest is texture)."""
    import cv2

    from panoworld.core.conventions import erp_pixel_solid_angle

    h, w = out.shape[:2]
    r0 = int(h * (1.0 - deg / 180.0))
    wt = np.broadcast_to(erp_pixel_solid_angle(h, w)[r0:], (h - r0, w))[..., None]
    err = out.astype(np.float32) - clean.astype(np.float32)
    low = cv2.GaussianBlur(err, (0, 0), 6)[r0:]
    err = err[r0:]
    total = max(float((wt * err**2).sum()), 1e-9)
    return {"under_share": float((wt * err**2 * mask[r0:, :, None]).sum()) / total,
            "lowfreq_share": float((wt * low**2).sum()) / total}
