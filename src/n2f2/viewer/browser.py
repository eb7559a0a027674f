"""Headless Chromium for driving the viewer page (its browser test and the screenshot of
``benchmarks/bench_viewer.py``). Playwright cannot download its own browser on these machines,
so Debian's ``chromium`` is used; the flags keep it from reaching out to the (closed) network."""

from __future__ import annotations

from typing import Any

CHROMIUM_PATH = "/usr/bin/chromium"  # Debian package `chromium`
CHROMIUM_ARGS = (
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
)


def launch_chromium(playwright: Any) -> Any:
    """A headless Debian Chromium browser from a ``sync_playwright()`` context."""
    return playwright.chromium.launch(executable_path=CHROMIUM_PATH, headless=True, args=list(CHROMIUM_ARGS))
