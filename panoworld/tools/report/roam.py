"""The report's roam section: Gaussian renders beside the reference per distance bucket, from `report --eval`."""

from __future__ import annotations

from panoworld.io.jsonio import read_json
from panoworld.tools.report import encode as enc
from panoworld.tools.report.page import Section, figure, fmt, missing, table
from panoworld.tools.report.scene_data import ROAM_IMAGES, ReportParams, SceneData, find_eval_json

LABELS = {"d0": "capture point", "d0.5": "~0.5 m", "d1": "~1 m", "d2": "~2 m", "far": "farthest"}
KINDS = (("erp", "Gaussians, ERP"), ("erp_ref", "reference, ERP"), ("pinhole", "Gaussians, pinhole"),
         ("pinhole_ref", "reference, pinhole"))


def section_roam(scene: SceneData, params: ReportParams) -> Section:
    title = "Roam: the scene away from the capture point"
    path = find_eval_json(scene, params.eval_json)
    roam = None
    if path is not None:
        try:
            roam = read_json(path)["stages"].get("roam")
        except (OSError, ValueError, KeyError, TypeError, AttributeError):
            roam = None
    if not isinstance(roam, dict) or roam.get("available") is False:
        why = roam.get("reason") if isinstance(roam, dict) else "no saved roam evaluation"
        return missing("roam", title, f"{why}: run `python runner.py report SCENE --eval`")
    img_dir = scene.art / ROAM_IMAGES
    rows, blocks = [], []
    for key, label in LABELS.items():
        count = roam.get(f"{key}_count", 0)
        rows.append([label, fmt(roam.get(f"{key}_range_m")), fmt(count), fmt(roam.get(f"{key}_erp_psnr")),
                     fmt(roam.get(f"{key}_erp_ssim")), fmt(roam.get(f"{key}_erp_coverage")),
                     fmt(roam.get(f"{key}_pinhole_psnr")), fmt(roam.get(f"{key}_pinhole_coverage"))])
        figs = []
        for kind, caption in KINDS:
            img = enc.read_rgb(img_dir / f"{key}_{kind}.png", params.image_width * (2 if "erp" in kind else 1))
            if img is not None:
                figs.append(figure(enc.data_uri(img), f"{label}: {caption}"))
        if figs:
            blocks.append(f'<h3>{label}</h3><div class="row">{"".join(figs)}</div>')
    head = ["distance", "range (m)", "views", "ERP PSNR", "ERP SSIM", "ERP coverage", "pinhole PSNR", "pinhole coverage"]
    note = (f'<p class="note">reference: {fmt(roam.get("reference"))}; ERP {fmt(roam.get("erp_size"))}, pinhole '
            f'{fmt(roam.get("pinhole"))}; poses at random on the NavMesh (docs/evaluation.md, roam protocol)</p>')
    if not blocks:
        note += f'<p class="note">no roam pictures in {img_dir}: `python runner.py report SCENE --eval` saves them</p>'
    return Section("roam", title, note + table(head, rows, set(range(2, 8))) + "".join(blocks))
