"""The dataset view of a precompute output: clip length/stride/track histograms and a strip of sample clips."""

from __future__ import annotations

import html
import time
from collections import Counter
from pathlib import Path

import numpy as np

from panoworld.io.jsonio import read_json
from panoworld.io.jsonl import read_jsonl
from panoworld.io.safe_write import write_text_atomic
from panoworld.tools.report import encode as enc
from panoworld.tools.report.page import Page, Section, figure, missing, table


def histogram_svg(counts: dict, label: str, width: int = 420, height: int = 120) -> str:
    """SVG bar chart of {value: count} with the values as x labels (sorted)."""
    keys = sorted(counts)
    n = max(len(keys), 1)
    cmax = max(list(counts.values()) + [1])
    bw = width / n
    bars = []
    for i, k in enumerate(keys):
        h = (height - 30) * counts[k] / cmax
        bars.append(f'<rect x="{i * bw + 1:.1f}" y="{height - 18 - h:.1f}" width="{max(bw - 2, 1):.1f}" height="{h:.1f}" '
                    f'fill="#4a7bd0"><title>{html.escape(str(k))}: {counts[k]}</title></rect>')
        if n <= 30 or i % max(1, n // 15) == 0:
            bars.append(f'<text x="{i * bw + bw / 2:.1f}" y="{height - 5}" font-size="10" text-anchor="middle">'
                        f"{html.escape(str(k))}</text>")
    return (f'<figure class="plot"><svg xmlns="http://www.w3.org/2000/svg" viewBox="0 0 {width} {height}" width="{width}" '
            f'height="{height}"><rect width="{width}" height="{height}" fill="#fff"/>{"".join(bars)}</svg>'
            f"<figcaption>{html.escape(label)} (max {cmax})</figcaption></figure>")


def read_index(cond_dir: Path) -> list[dict]:
    from panoworld.tools.precompute.run import INDEX

    return read_jsonl(cond_dir / INDEX)


def clip_strip(cond_dir: Path, row: dict, width: int) -> str:
    """Condition, mask and target of a clip's middle frame, side by side."""
    from panoworld.io.conditions import load_conditions

    cdir = cond_dir / row["path"]
    cond = load_conditions(cond_dir / row["conditions"])
    if not len(cond):
        return ""
    i = len(cond) // 2
    rgb = enc.shrink(cond.rgb[i], width)
    mask = enc.shrink(cond.mask[i].astype(np.uint8) * 255, width, nearest=True)
    target = enc.read_rgb(cdir / "target" / f"{i:06d}.png", width)
    name = (f"{row['scene']}/{row['clip']} · track {row.get('track')} · frames {row.get('length')} · "
            f"stride {row.get('stride')} · shown: frame {i}")
    figs = []
    if rgb is not None:
        figs.append(figure(enc.data_uri(rgb), "condition"))
    if mask is not None:
        figs.append(figure(enc.data_uri((mask > 0).astype(np.uint8) * 255, "png"), f"mask (fill {100 * (mask == 0).mean():.1f} %)"))
    if target is not None:
        figs.append(figure(enc.data_uri(target), "target"))
    return f'<p class="note">{html.escape(name)}</p><div class="row">{"".join(figs)}</div>'


def build_dataset_report(cond_dir: Path, out: Path | None = None, *, clips: int = 12, width: int = 256) -> Path:
    """Write COND_DIR/report.html (or out): histograms of the index and a strip of `clips` sample clips."""
    from panoworld.tools.precompute.run import FAILURES, SUMMARY
    from panoworld.tools.report.scene_data import subsample

    cond_dir = Path(cond_dir)
    out = Path(out) if out else cond_dir / "report.html"
    rows = read_index(cond_dir)
    page = Page(f"PanoWorld dataset report: {cond_dir.resolve().name}",
                f"{cond_dir.resolve()} · {len(rows)} clips · written {time.strftime('%Y-%m-%d %H:%M:%S UTC', time.gmtime())}")
    summary = read_json(cond_dir / SUMMARY, default={})
    scenes = Counter(r["scene"] for r in rows)
    facts = [["clips", len(rows)], ["scenes", len(scenes)],
             ["frames", sum(int(r.get("length", 0)) for r in rows)]]
    facts += [[k, v] for k, v in summary.items() if not isinstance(v, (dict, list))]
    fails = read_jsonl(cond_dir / FAILURES, missing_ok=True)
    body = table(["dataset", "value"], facts)
    if fails:
        body += table(["failed scene", "clip", "error"], [[f.get("scene"), f.get("clip"), f.get("error")] for f in fails])
    page.add(Section("summary", "Summary", body))
    if not rows:
        page.add(missing("histograms", "Clip statistics", "index.jsonl lists no clips"))
        page.add(missing("clips", "Sample clips", "index.jsonl lists no clips"))
    else:
        hists = [
            histogram_svg(Counter(int(r["length"]) for r in rows), "clip length (frames)"),
            histogram_svg(Counter(int(r["stride"]) for r in rows), "stride"),
            histogram_svg(Counter(f"{r['scene']}:{r['track']}" if len(scenes) <= 6 else int(r["track"]) for r in rows),
                          "track (scene:track)" if len(scenes) <= 6 else "track index"),
            histogram_svg(Counter(scenes), "clips per scene"),
        ]
        page.add(Section("histograms", "Clip statistics", f'<div class="row">{"".join(hists)}</div>'))
        picks = [rows[i] for i in subsample(len(rows), clips)]
        strips = []
        for r in picks:
            try:
                strips.append(clip_strip(cond_dir, r, width))
            except (OSError, ValueError, KeyError) as e:
                strips.append(f'<p class="note bad">{html.escape(r.get("path", "?"))}: {html.escape(str(e))}</p>')
        page.add(Section("clips", "Sample clips (condition, mask, target)",
                         f'<p class="note">{len(picks)} of {len(rows)} clips, spread over the index</p>' + "".join(strips)))
    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_atomic(out, page.render())
    return out
