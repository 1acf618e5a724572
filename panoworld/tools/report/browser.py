"""Headless Chromium (the system's /usr/bin/chromium, driven by Playwright) for report and viewer tests and screenshots."""

from __future__ import annotations

import os
import shutil
import tempfile
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

CHROMIUM_CANDIDATES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FLAGS = [
    "--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
    "--disable-background-networking", "--disable-component-update", "--disable-sync",
    "--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--ignore-gpu-blocklist",
]


def chromium_path() -> str:
    """The system Chromium ($PANOWORLD_CHROMIUM, else chromium on PATH); a clear error naming the install command."""
    env = os.environ.get("PANOWORLD_CHROMIUM")
    if env:
        return env
    for name in CHROMIUM_CANDIDATES:
        found = shutil.which(name)
        if found:
            return found
    raise FileNotFoundError("no Chromium found: install it (Debian: apt-get install -y chromium) or set PANOWORLD_CHROMIUM")


@dataclass
class Console:
    """Console messages and uncaught page errors seen while a page was open."""

    errors: list[str] = field(default_factory=list)
    messages: list[str] = field(default_factory=list)


@contextmanager
def browser_page(width: int = 1400, height: int = 900):
    """Yield (page, console) of a fresh headless Chromium with software WebGL and a throw-away profile."""
    try:
        from playwright.sync_api import sync_playwright
    except ImportError as e:
        raise ImportError("driving Chromium needs Playwright: pip install '.[dev]'") from e
    profile = tempfile.mkdtemp(prefix="panoworld-chromium-")
    console = Console()
    try:
        with sync_playwright() as pw:
            ctx = pw.chromium.launch_persistent_context(
                profile, executable_path=chromium_path(), headless=True, args=FLAGS,
                viewport={"width": width, "height": height},
            )
            try:
                page = ctx.pages[0] if ctx.pages else ctx.new_page()
                page.on("console", lambda m: (console.errors if m.type == "error" else console.messages).append(m.text))
                page.on("pageerror", lambda e: console.errors.append(f"pageerror: {e}"))
                yield page, console
            finally:
                ctx.close()
    finally:
        shutil.rmtree(profile, ignore_errors=True)


def screenshot_array(page, path: Path | None = None, full_page: bool = False, clip: dict | None = None,
                     timeout_s: float = 120.0):
    """(H, W, 3) uint8 RGB of the page (optionally also written to path as PNG); software WebGL can be slow."""
    import cv2
    import numpy as np

    png = page.screenshot(full_page=full_page, clip=clip, timeout=timeout_s * 1000)
    if path is not None:
        Path(path).write_bytes(png)
    img = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_COLOR)
    return img[..., ::-1]
