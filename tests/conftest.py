"""Shared fixtures. ``trained_run`` builds one tiny end-to-end run of the real pipeline (demo scene
-> fitted Gaussians -> ground-truth segment bank with MiniLM caption embeddings -> nested field)
once per test session, through the same CLI commands a user runs."""

from __future__ import annotations

import contextlib
import os
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

# Two cores: keep torch from oversubscribing when pytest and a server thread both compute.
os.environ.setdefault("OMP_NUM_THREADS", "2")
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # see n2f2/cli.py
os.environ.setdefault("HF_HUB_OFFLINE", "1")


@dataclass(frozen=True)
class TrainedRun:
    scene_dir: Path
    run_dir: Path
    bank_dir: Path
    num_views: int
    part_query: str = "lid of the teapot"


@pytest.fixture(scope="session")
def tiny_random_clip():
    """A randomly initialised CLIP (2 layers, 32 wide, 16-d embeddings) and its tokenizer: the
    real CLIP code path at a size tests can afford."""
    import torch
    from transformers import CLIPConfig, CLIPModel, CLIPTokenizer

    torch.manual_seed(0)
    cfg = CLIPConfig(
        text_config=dict(vocab_size=8, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=2, max_position_embeddings=77, bos_token_id=0, eos_token_id=1,
                         pad_token_id=1),
        vision_config=dict(image_size=32, patch_size=8, hidden_size=32, intermediate_size=64,
                           num_hidden_layers=2, num_attention_heads=2),
        projection_dim=16)
    return CLIPModel(cfg), CLIPTokenizer()


def _cli(*argv) -> None:
    from n2f2.cli import main

    rc = main([str(a) for a in argv])
    assert rc == 0, f"n2f2 {' '.join(map(str, argv))} exited {rc}"


@pytest.fixture(scope="session")
def trained_run(tmp_path_factory) -> TrainedRun:
    from n2f2.data.synthetic import generate_demo_scene

    root = tmp_path_factory.mktemp("trained_run")
    scene = root / "scene"
    num_views = 6
    generate_demo_scene(scene, num_views=num_views, width=80, height=60, seed=0,
                        labelled_views=[1, 4], show_progress=False)
    fit = root / "fit"
    _cli("fit-gaussians", scene, "--out", fit, "--steps", 60, "--quiet")
    bank = root / "bank"
    _cli("segments", scene, "--gaussians", fit / "gaussians.ply", "--segmenter", "ground-truth",
         "--encoder", "captions", "--out", bank, "--quiet")
    run = root / "run"
    _cli("train", scene, "--gaussians", fit / "gaussians.ply", "--segments", bank, "--out", run,
         "--iterations", 80, "--pixels-per-step", 1024, "--dim", 32, "--plane-resolution", 32,
         "--plane-channels", 8, "--hidden", 64, "--train-on-all", "--quiet")
    return TrainedRun(scene_dir=scene, run_dir=run, bank_dir=bank, num_views=num_views)


@pytest.fixture
def wait():
    """``wait(predicate, timeout_s, what)``: poll ``predicate`` every 0.1 s until it holds, else
    fail naming ``what`` (the browser tests wait on pages and websockets)."""

    def wait_until(predicate, timeout: float, what: str) -> None:
        deadline = time.time() + timeout
        while not predicate():
            if time.time() > deadline:
                raise AssertionError(f"timed out waiting for {what}")
            time.sleep(0.1)

    return wait_until


@pytest.fixture
def viewer_page(wait):
    """``with viewer_page(running, width, height, ready) as (page, client)``: the 3D viewer that
    ``running`` serves, open in headless Chromium once the text ``ready`` shows, its software
    WebGL toast closed, and the page's viser client (the browser tests' common opening)."""

    @contextlib.contextmanager
    def open_page(running, width: int, height: int, ready: str):
        sync_api = pytest.importorskip("playwright.sync_api")
        from n2f2.viewer.browser import launch_chromium

        known = set(running.viser.get_clients())
        with sync_api.sync_playwright() as p:
            browser = launch_chromium(p)
            try:
                page = browser.new_page(viewport={"width": width, "height": height})  # software WebGL: small is fast
                page.goto(running.url)
                page.wait_for_selector(f"text={ready}", timeout=120_000)
                # Headless Chromium renders WebGL in software; viser says so in a toast. Closed by
                # a DOM click: the page may be too busy drawing for a pointer one.
                toast = page.locator(".mantine-Notification-root").filter(has_text="Software WebGL").locator("button")
                if toast.count():
                    toast.first.evaluate("button => button.click()")
                wait(lambda: set(running.viser.get_clients()) - known, 60, "the page's websocket")
                yield page, running.viser.get_clients()[max(set(running.viser.get_clients()) - known)]
            finally:
                browser.close()

    return open_page
