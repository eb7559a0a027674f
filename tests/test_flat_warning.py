"""Honest outputs for a flat relevancy map (the rule, the console line, query.json, the heatmap,
the JSON API), and one localisation rule: ``n2f2 query``, ``/api/query`` and the evaluation's
function give the same point for the same view and query."""

from __future__ import annotations

import base64
import io
import json
import shutil

import numpy as np
import pytest

from n2f2.query.maps import FLAT_RANGE, flat_warning, is_flat, relevancy_range
from n2f2.query.outputs import HEATMAP_ALPHA, heat_values, heatmap_overlay, normalize01, relevancy_colors

VIEW = 1  # a labelled view of the shared demo run


def _flat(seed: int = 0) -> np.ndarray:  # [60, 80] relevancy spanning 0.4999987 .. 0.5000009
    rng = np.random.default_rng(seed)
    return (0.5 + rng.uniform(-1.3e-6, 0.9e-6, (60, 80))).astype(np.float32)


def _real() -> np.ndarray:  # [60, 80] a blob of relevancy 0.8 over a 0.35 background
    y, x = np.mgrid[0:60, 0:80]
    return (0.35 + 0.45 * np.exp(-((x - 50) ** 2 + (y - 20) ** 2) / 60.0)).astype(np.float32)


def _png(path_or_b64) -> np.ndarray:
    from PIL import Image

    if isinstance(path_or_b64, str):
        return np.asarray(Image.open(io.BytesIO(base64.b64decode(path_or_b64))))
    return np.asarray(Image.open(path_or_b64))


def test_a_flat_map_is_flagged_and_a_real_one_is_not():
    flat, real = _flat(), _real()
    assert relevancy_range(flat) < 3e-6 and is_flat(flat)
    msg = flat_warning(flat)
    assert msg is not None and msg.startswith("relevancy is flat over this view (range ")
    assert msg.endswith(" < 1e-03): the answer carries no signal")
    assert flat_warning(np.full((4, 4), 0.5, np.float32)) == (
        "relevancy is flat over this view (range 0.0e+00 < 1e-03): the answer carries no signal"
    )
    assert not is_flat(real) and flat_warning(real) is None
    # The threshold is the stated constant: a range just below it is flat, just above it is not.
    ramp = np.linspace(0.0, 1.0, 64, dtype=np.float32).reshape(8, 8)
    assert is_flat(0.5 + 0.99 * FLAT_RANGE * ramp) and not is_flat(0.5 + 1.01 * FLAT_RANGE * ramp)
    assert "over the Gaussians" in flat_warning(flat.ravel(), "the Gaussians")


def test_a_flat_map_is_drawn_as_one_colour_and_a_real_one_stretched():
    from matplotlib import colormaps

    flat, real = _flat(), _real()
    v = heat_values(flat)
    assert np.ptp(v) == 0 and v[0, 0] == pytest.approx(0.5, abs=1e-5)  # absolute scale, not stretched
    colors = relevancy_colors(flat)
    assert np.ptp(colors.reshape(-1, 3), axis=0).max() == 0
    np.testing.assert_allclose(colors[0, 0], colormaps["turbo"](float(flat.mean()))[:3], atol=1e-6)
    over_black = heatmap_overlay(np.zeros((60, 80, 3), np.float32), flat)
    assert np.ptp(over_black.reshape(-1, 3), axis=0).max() == 0
    np.testing.assert_array_equal(heat_values(real), normalize01(real))  # a real map: min-max, as before


@pytest.fixture(scope="module")
def flat_run(trained_run, tmp_path_factory):
    """A copy of the shared demo run whose field's output weights W are zero: every feature is 0,
    every relevancy exactly 0.5 (see n2f2.field.relevancy)."""
    import torch

    from n2f2.field import load_field, save_field

    run = tmp_path_factory.mktemp("flat") / "run"
    shutil.copytree(trained_run.run_dir, run)
    field, meta = load_field(run / "field.pt")
    with torch.no_grad():
        field.W.zero_()
    save_field(run / "field.pt", field, meta)
    return run


def _query(run, trained_run, out, texts, capsys) -> tuple[dict, list[str]]:
    from n2f2.cli import main

    scene = str(trained_run.scene_dir)
    assert main(["query", str(run), *texts, "--views", str(VIEW), "--scene", scene, "--out", str(out), "--quiet"]) == 0
    return json.loads((out / "query.json").read_text()), capsys.readouterr().out.splitlines()


def test_query_on_a_flat_field_warns_and_draws_one_colour(flat_run, trained_run, tmp_path, capsys):
    from matplotlib import colormaps

    out = tmp_path / "q"
    summary, lines = _query(flat_run, trained_run, out, ["teapot"], capsys)
    want = 'warning: "teapot": relevancy is flat over this view (range 0.0e+00 < 1e-03): the answer carries no signal'
    assert want in lines
    assert lines[lines.index(want) - 1].startswith(f"{summary['views'][0]['view']}  'teapot': max relevancy 0.500")
    rec = summary["views"][0]["queries"][0]
    assert rec["warning"] == want.split('"teapot": ', 1)[1]
    # The heatmap PNG: one colour (turbo at 0.5) at one opacity over the RGB.
    heat = _png(out / rec["files"]["heatmap"]) / 255.0
    rgb = _png(out / f"{rec['view']}_rgb.png") / 255.0
    a = HEATMAP_ALPHA * 0.5
    implied = (heat - rgb * (1 - a)) / a  # the colour the heatmap laid over the RGB
    np.testing.assert_allclose(implied, np.broadcast_to(colormaps["turbo"](0.5)[:3], implied.shape), atol=3 / 255 / a)


def test_the_api_says_a_flat_map_is_flat(flat_run, trained_run):
    pytest.importorskip("fastapi")
    from n2f2.query.engine import QueryEngine
    from n2f2.viewer.server import Viewer

    viewer = Viewer(QueryEngine.from_run(flat_run, scene=trained_run.scene_dir))
    _, results = viewer.render_and_query(f"view:{VIEW}", VIEW, ["teapot"], "composite")
    assert results[0]["warning"].startswith("relevancy is flat over this view")
    heat = _png(results[0]["relevancy_png"])
    assert np.ptp(heat.reshape(-1, heat.shape[-1]), axis=0).max() == 0  # one colour


def test_one_localisation_rule_for_query_api_and_eval(trained_run, tmp_path, capsys):
    """Same view, same query: query.json's point, the API handler's and the evaluation's agree,
    in integer pixel coordinates of the view as rendered, with the same box size by default."""
    pytest.importorskip("fastapi")
    from n2f2.eval.protocol import evaluate_frame_category, localization_hit, localization_point
    from n2f2.query.engine import QueryEngine
    from n2f2.query.maps import localization_maxima
    from n2f2.viewer.server import Viewer

    text = trained_run.part_query
    summary, lines = _query(trained_run.run_dir, trained_run, tmp_path / "q", [text], capsys)
    view = summary["views"][0]
    rec = view["queries"][0]
    assert "warning" not in rec and not any(line.startswith("warning:") for line in lines)
    cli = (rec["localization"]["x"], rec["localization"]["y"])

    viewer = Viewer(QueryEngine.from_run(trained_run.run_dir, scene=trained_run.scene_dir))
    cache, results = viewer.render_and_query(f"view:{VIEW}", VIEW, [text], "composite")
    assert (cache.width, cache.height) == (view["width"], view["height"])  # the same render size
    assert viewer.box_pixels(cache.width) == view["box_size"]  # the same default box
    assert "warning" not in results[0]
    api = tuple(results[0]["localization"])
    assert all(isinstance(v, int) for v in api)

    rel = np.load(tmp_path / "q" / rec["files"]["relevancy"])
    ev = localization_point(rel, view["box_size"])
    assert cli == api == ev
    # The evaluation scores a hit at that point: it is one of the maxima, both through the
    # one-level test and the scene scorer's stacked path.
    assert list(ev) in localization_maxima(rel, view["box_size"]).tolist()
    box = np.array([[ev[0], ev[1], ev[0], ev[1]]], np.float64)
    assert localization_hit(rel, box, view["box_size"])
    assert evaluate_frame_category(rel, np.ones(rel.shape, bool), box, view["box_size"]).hit


def test_the_3d_colours_of_a_flat_query_are_on_the_absolute_scale():
    from n2f2.viewer.splat_colors import heat_index, normalized_relevancy

    flat = np.full((1, 50), 0.5, np.float32)
    flat[0, ::7] += 2e-4  # rounding noise, below FLAT_RANGE
    v = normalized_relevancy(flat)
    assert np.ptp(v) == 0 and v[0] == pytest.approx(0.5, abs=1e-3)  # one colour: turbo's middle
    assert set(heat_index(flat).tolist()) == {128}
    real = np.linspace(0.3, 0.7, 50, dtype=np.float32)[None]
    np.testing.assert_allclose(normalized_relevancy(real), np.linspace(0, 1, 50), atol=1e-6)  # min-max, as before
