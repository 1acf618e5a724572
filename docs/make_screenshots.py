"""README screenshots of a scene's report and viewer: python docs/make_screenshots.py [SCENE_DIR] [--out docs/img].

SCENE_DIR defaults to the demo scene (`python runner.py demo` writes demo_out/scene). Each PNG is shrunk until it
is under 300 KB. Needs Chromium (Debian: apt-get install chromium) and the dev extras (Playwright).
"""

from __future__ import annotations

import argparse
import json
import re
import socket
import sys
import time
from pathlib import Path

import cv2
import numpy as np

ROOT = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(ROOT))

MAX_BYTES = 300_000


def save_small(img: np.ndarray, path: Path, width: int = 1100) -> None:
    """Write RGB img as PNG, narrowing it until the file is under MAX_BYTES."""
    while True:
        h = round(img.shape[0] * min(1.0, width / img.shape[1]))
        small = cv2.resize(img, (min(width, img.shape[1]), h), interpolation=cv2.INTER_AREA)
        ok, buf = cv2.imencode(".png", small[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9])
        if len(buf) <= MAX_BYTES or width < 300:
            path.write_bytes(buf.tobytes())
            print(f"{path} {small.shape[1]}x{small.shape[0]} {len(buf) / 1e3:.0f} KB")
            return
        width = int(width * 0.85)


def report_shots(scene: Path, out: Path) -> None:
    from panoworld.tools.report.browser import browser_page, screenshot_array
    from panoworld.tools.report.cli import build_scene_report

    html = build_scene_report(scene)
    with browser_page(1280, 900) as (page, console):
        page.goto(html.resolve().as_uri())
        page.wait_for_load_state("load")
        labels = json.loads(page.locator("#report-data").text_content()).get("frames", {}).get("text", {}).get("label", [])
        fills = [float(m.group(1)) if (m := re.search(r"fill ([0-9.]+) %", t)) else 0.0 for t in labels]
        if fills:  # show the frame with the most to generate
            page.locator('input[data-slider="frames"]').fill(str(int(np.argmax(fills))))
        for sec in ("plan", "frames", "gaussians"):
            el = page.locator(f"section#{sec}")
            el.scroll_into_view_if_needed()
            box = el.bounding_box()
            tallest = 620 if sec == "gaussians" else 900
            clip = {"x": box["x"], "y": box["y"], "width": box["width"], "height": min(box["height"], tallest)}
            img = screenshot_array(page, clip=clip)
            save_small(img, out / f"report_{sec}.png")
        if console.errors:
            print("console errors:", console.errors, file=sys.stderr)


def viewer_shot(scene: Path, out: Path) -> None:
    from panoworld.tools.report.browser import browser_page, screenshot_array
    from panoworld.tools.viewer.app import SceneViewer, ViewerParams

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    viewer = SceneViewer(scene, ViewerParams(port=port))
    try:
        with browser_page(1000, 600) as (page, _):
            page.goto(viewer.url)
            page.wait_for_selector("canvas", timeout=60_000)
            time.sleep(3)
            page.add_style_tag(content=".mantine-Notification-root{display:none!important}")  # "software WebGL" notice
            for client in viewer.server.get_clients().values():  # a step back and up from the first camera
                client.camera.position = (0.0, -0.5, -1.2)
                client.camera.look_at = (0.0, 0.6, 1.5)
            if viewer._poses is not None and len(viewer._poses) > 2:
                viewer.handles["frame_slider"].value = len(viewer._poses) // 3
            prev = None
            for _ in range(10):  # software WebGL: wait for two equal frames
                time.sleep(1.0)
                img = screenshot_array(page)
                if prev is not None and np.abs(img.astype(int) - prev).mean() < 0.5:
                    break
                prev = img.astype(int)
            save_small(img, out / "viewer.png")
    finally:
        viewer.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", type=Path, nargs="?", default=Path("demo_out/scene"))
    ap.add_argument("--out", type=Path, default=ROOT / "docs" / "img")
    ap.add_argument("--only", choices=["report", "viewer"], help="make only these screenshots")
    args = ap.parse_args(argv)
    if not (args.scene / "artifacts").is_dir():
        print(f"error: {args.scene}: no artifacts/ (run `python runner.py demo` first)", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    if args.only != "viewer":
        report_shots(args.scene, args.out)
    if args.only != "report":
        viewer_shot(args.scene, args.out)
    return 0


if __name__ == "__main__":
    sys.exit(main())
