"""The fit's scene-sized cpu preset, coarse-to-fine schedule, initial-scale clamp, pixel-coloured
random initialisation, screen-size pruning and held-out renders."""

from __future__ import annotations

import json
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

from n2f2.cameras import Camera, look_at
from n2f2.cli import main as cli_main
from n2f2.data.scene import Scene
from n2f2.gaussians import Gaussians, write_ply
from n2f2.gaussians.fit import downsample_image, fit_gaussians, initial_gaussians, resolution_factor
from n2f2.gaussians.fit_config import FitConfig
from n2f2.gaussians.optim import DensifyStats, GaussianAdam, densify_and_prune
from n2f2.gaussians.init import init_from_points, random_points_in_frusta
from n2f2.gaussians.model import sh_to_rgb
from n2f2.gaussians.orbit import orbit_cameras, render_views
from n2f2.io import write_png


def _ring(n: int, w: int, h: int, radius: float = 4.0) -> list[Camera]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        R, t = look_at(np.array([radius * np.cos(a), radius * np.sin(a), 1.0]), np.zeros(3))
        cams.append(Camera(1.1 * w, 1.1 * w, w / 2, h / 2, w, h, R=R, t=t))
    return cams


def _scene(tmp_path: Path, n: int, w: int, h: int, colors=None, points=None) -> Scene:
    """Views of constant colour (view i: ``colors[i]``), written as PNGs."""
    cams = _ring(n, w, h)
    paths = []
    for i in range(n):
        c = np.full((h, w, 3), 0.5 if colors is None else colors[i], np.float32)
        paths.append(tmp_path / "images" / f"frame_{i + 1:05d}.png")
        write_png(paths[-1], c)
    pts = None if points is None else np.asarray(points, np.float64)
    cols = None if pts is None else np.full(pts.shape, 128, np.uint8)
    return Scene(root=tmp_path, cameras=cams, image_paths=paths, points=pts, point_colors=cols)


# ------------------------------------------------------------------------------------ sizing
def test_sized_for_derives_steps_cap_and_windows_from_the_scene(tmp_path):
    # 40 views, every 8th held out -> 35 training views; 160 x 120 pixels.
    demo_like = FitConfig.cpu().sized_for(_scene(tmp_path / "a", 40, 160, 120))
    assert demo_like.steps == 1500  # 43 x 35 = 1505, to the nearest 100
    assert demo_like.max_gaussians == 12_000  # 0.625 x 19,200
    assert (demo_like.densify_from, demo_like.densify_until, demo_like.sh_degree_interval) == (200, 1100, 400)
    assert demo_like.coarse_until == () and demo_like.means_lr_max_steps == 1500

    # 80 views (70 training), 320 x 240: 43 x 70 = 3010 -> 2000 steps (the upper bound), cap 48,000,
    # windows scaled by 4/3, and a coarse first half at sqrt(76,800 / 25,000) = 1.753.
    big = FitConfig.cpu().sized_for(_scene(tmp_path / "b", 80, 320, 240))
    assert big.steps == 2000 and big.max_gaussians == 48_000
    assert (big.densify_from, big.densify_until, big.sh_degree_interval) == (267, 1467, 533)
    assert big.coarse_until == (0.5,)
    assert big.coarse_downscale[0] == pytest.approx(math.sqrt(76_800 / 25_000))

    # The background is learned only for a backdrop the sparse points miss: none here (no points),
    # but not for points on a sphere around the whole ring, which cover every cell of every view.
    assert demo_like.background_sh_degree == 2 and demo_like.background_from_images
    rng = np.random.default_rng(0)
    d = rng.normal(size=(40_000, 3))
    shell = 20.0 * d / np.linalg.norm(d, axis=1, keepdims=True)
    covered = FitConfig.cpu().sized_for(_scene(tmp_path / "d", 40, 160, 120, points=shell))
    assert covered.background_sh_degree == -1 and not covered.background_from_images

    # Few views: the lower bound; an explicit step count keeps the fractions.
    few = FitConfig.cpu().sized_for(_scene(tmp_path / "c", 9, 32, 24))
    assert few.steps == 1000 and few.max_gaussians == 2000  # 0.625 x 768 = 480, raised to the floor
    given = FitConfig.cpu().sized_for(_scene(tmp_path / "c", 9, 32, 24), steps=300)
    assert (given.steps, given.densify_from, given.densify_until) == (300, 40, 220)


def test_random_init_resets_opacity_twice_inside_the_densification_window(tmp_path):
    no_points = _scene(tmp_path / "b", 80, 320, 240)  # 2000 steps, densification until 1467
    rng = np.random.default_rng(0)
    with_points = _scene(tmp_path / "p", 80, 320, 240, points=rng.normal(size=(500, 3)))
    # Random init (asked for, or implied by a scene without points): 0.35 x 2000 = 700, so
    # resets at steps 700 and 1400, both before densification ends.
    for cfg in (FitConfig.cpu().sized_for(no_points), FitConfig.cpu().sized_for(with_points, init="random")):
        assert cfg.opacity_reset_every == 700
        assert [s for s in range(1, cfg.steps + 1)
                if s % cfg.opacity_reset_every == 0 and s < cfg.densify_until] == [700, 1400]
    # Points in a small cluster leave most of every view's cells empty (a backdrop): 2 x 5000
    # random Gaussians join them where the views overlap, and the same resets.
    clustered = FitConfig.cpu().sized_for(with_points)
    assert clustered.background_sh_degree == 2  # the backdrop rule's own sign
    assert (clustered.opacity_reset_every, clustered.init_extra_seen) == (700, 10_000)
    # Points covering every view (a sphere around the ring) or a trained PLY: no reset, no extra.
    d = rng.normal(size=(40_000, 3))
    covering = _scene(tmp_path / "s", 80, 320, 240, points=20.0 * d / np.linalg.norm(d, axis=1, keepdims=True))
    assert (FitConfig.cpu().sized_for(covering).opacity_reset_every, FitConfig.cpu().sized_for(covering).init_extra_seen) == (0, 0)
    trained = init_from_points(rng.normal(size=(8, 3)), np.full((8, 3), 128, np.uint8))
    assert FitConfig.cpu().sized_for(no_points, init=trained).opacity_reset_every == 0
    assert FitConfig.cpu().sized_for(no_points, init=trained).init_extra_seen == 0


def test_resolution_factor_follows_the_schedule():
    cfg = replace(FitConfig(), steps=1000, coarse_until=(0.2, 0.5), coarse_downscale=(4.0, 2.0))
    assert [resolution_factor(cfg, s) for s in (1, 200, 201, 500, 501, 1000)] == [4, 4, 2, 2, 1, 1]
    assert resolution_factor(FitConfig(), 1) == 1.0


def test_downsample_image_is_the_block_mean():
    img = torch.arange(4 * 6 * 3, dtype=torch.float32).reshape(4, 6, 3)
    small = downsample_image(img, 2, 3)
    expected = img.numpy().reshape(2, 2, 3, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(small.numpy(), expected)
    assert downsample_image(img, 4, 6) is img


# ------------------------------------------------------------------------------------ init
def test_random_points_take_the_colour_of_their_pixel(tmp_path):
    colors = [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)]
    scene = _scene(tmp_path, 3, 16, 12, colors=colors)
    pts, cols = random_points_in_frusta(scene.cameras, 300, 1.0, 2.0, seed=0, images=scene.image)
    # each point lies in front of one camera at z-depth in [1, 2] and has that view's colour
    for p, c in zip(pts, cols):
        owners = []
        for i, cam in enumerate(scene.cameras):
            pc = cam.R @ p + cam.t
            u, v = cam.fx * pc[0] / pc[2] + cam.cx, cam.fy * pc[1] / pc[2] + cam.cy
            if 1.0 - 1e-9 <= pc[2] <= 2.0 + 1e-9 and 0 <= u <= cam.width and 0 <= v <= cam.height:
                owners.append(i)
        assert any(tuple(c) == tuple(int(255 * x) for x in colors[i]) for i in owners)


def test_random_init_is_coloured_by_the_training_views(tmp_path):
    scene = _scene(tmp_path, 8, 16, 12, colors=[(0.2, 0.4, 0.6)] * 8)
    cfg = replace(FitConfig(), random_init_count=200, sh_degree=0)
    g = initial_gaussians(scene, cfg, "random")
    rgb = sh_to_rgb(g.sh[:, 0].detach())
    torch.testing.assert_close(rgb, torch.tensor([[0.2, 0.4, 0.6]]).expand(200, 3), atol=3e-3, rtol=0)


def test_extra_random_points_and_scale_clamp(tmp_path):
    # 3 points at the origin region, seen at z-depth ~4 by every camera of the ring
    points = [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0]]
    scene = _scene(tmp_path, 8, 16, 12, points=points)
    plain = initial_gaussians(scene, replace(FitConfig(), sh_degree=0), None)
    assert plain.num == 3
    cfg = replace(FitConfig(), sh_degree=0, init_extra_random=10.0, init_max_scale=0.01)
    g = initial_gaussians(scene, cfg, None)
    assert g.num == 3 + 30
    torch.testing.assert_close(g.means[:3].detach(), torch.tensor(points))
    assert float(g.scales.detach().max()) <= 0.01 * scene.extent() * (1 + 1e-5)
    # The extra points lie on a sphere around the cameras' centroid, twice as far as the
    # farthest camera (the points are nearer than that), so behind the scene from every camera.
    centers = np.stack([c.center for c in scene.cameras[1:]])  # view 0 is held out
    centroid = centers.mean(0)
    radius = 2 * np.linalg.norm(centers - centroid, axis=1).max()
    extra = g.means[3:].detach().double().numpy()
    np.testing.assert_allclose(np.linalg.norm(extra - centroid, axis=1), radius, rtol=1e-4)


def test_extra_seen_points_lie_where_the_training_views_overlap(tmp_path):
    # 3 sparse points, plus 40 random Gaussians each inside at least half of the 7 training
    # views (view 0 is held out) and no nearer than 0.2 x extent to a camera that sees it,
    # coloured by the views (all one colour here).
    points = [[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.3, 0.0]]
    scene = _scene(tmp_path, 8, 16, 12, colors=[(0.2, 0.4, 0.6)] * 8, points=points)
    cfg = replace(FitConfig(), sh_degree=0, init_extra_seen=40, random_init_min_seen=0.5)
    g = initial_gaussians(scene, cfg, None)
    assert g.num == 3 + 40
    torch.testing.assert_close(g.means[:3].detach(), torch.tensor(points))
    extra = g.means[3:].detach().double().numpy()
    seen = np.zeros(40)
    for cam in scene.cameras[1:]:
        # pinhole projection written out: x_cam = R x + t, u = fx x/z + cx
        xc = extra @ cam.R.T + cam.t
        u = cam.fx * xc[:, 0] / xc[:, 2] + cam.cx
        v = cam.fy * xc[:, 1] / xc[:, 2] + cam.cy
        inside = (xc[:, 2] > 0) & (u >= 0) & (u <= cam.width) & (v >= 0) & (v <= cam.height)
        assert not np.any(inside & (xc[:, 2] < 0.2 * scene.extent()))
        seen += inside
    assert np.all(seen >= 0.5 * 7)
    rgb = sh_to_rgb(g.sh[3:, 0].detach())
    torch.testing.assert_close(rgb, torch.tensor([[0.2, 0.4, 0.6]]).expand(40, 3), atol=3e-3, rtol=0)


def test_clear_of_cameras_by_hand():
    R, t = look_at(np.array([0.0, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), up=(0.0, -1.0, 0.0))
    cam = Camera(10.0, 10.0, 5.0, 5.0, 10, 10, R=R, t=t)  # at the origin, looking down +z
    pts = np.array([[0.0, 0.0, 0.5],  # seen at depth 0.5 < 1: not clear
                    [0.0, 0.0, 2.0],  # seen at depth 2: clear
                    [5.0, 0.0, 0.5],  # outside the image: clear
                    [0.0, 0.0, -0.5]])  # behind the camera: clear
    from n2f2.gaussians.init import clear_of_cameras

    assert clear_of_cameras(pts, [cam], near=1.0).tolist() == [False, True, True, True]
    # A second camera 10 to the right, looking the same way: it sees none of the points, so
    # each is seen by at most half of the two cameras.
    other = Camera(10.0, 10.0, 5.0, 5.0, 10, 10, R=R, t=t - R @ np.array([10.0, 0.0, 0.0]))
    assert clear_of_cameras(pts, [cam, other], near=1.0, min_seen=0.5).tolist() == [False, True, False, False]
    assert clear_of_cameras(pts, [cam, other], near=1.0, min_seen=0.75).tolist() == [False] * 4


def test_random_init_keeps_clear_of_every_camera_and_fills_the_shell(tmp_path):
    scene = _scene(tmp_path, 8, 16, 12)
    cfg = replace(FitConfig(), random_init_count=400, sh_degree=0, random_init_shell=0.25)
    g = initial_gaussians(scene, cfg, "random")
    assert g.num == 400
    near = cfg.random_init_depth[0] * scene.extent()
    means = g.means.detach().double().numpy()
    for cam in scene.cameras[1:]:  # the training views
        pc = means @ cam.R.T + cam.t
        u, v = cam.fx * pc[:, 0] / pc[:, 2] + cam.cx, cam.fy * pc[:, 1] / pc[:, 2] + cam.cy
        seen = (pc[:, 2] > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
        assert (pc[seen, 2] >= near - 1e-9).all()
    centers = np.stack([c.center for c in scene.cameras[1:]])
    dist = np.linalg.norm(means - centers.mean(0), axis=1)
    on_shell = np.isclose(dist, 2 * np.linalg.norm(centers - centers.mean(0), axis=1).max(), rtol=1e-4)
    assert on_shell.sum() == 100


def test_background_from_images_is_the_border_median_and_is_recorded(tmp_path):
    # Views with a (0.2, 0.4, 0.6) frame around a white centre: the border ring is all frame.
    scene = _scene(tmp_path / "scene", 9, 16, 12)
    for path in scene.image_paths:
        img = np.ones((12, 16, 3), np.float32)
        img[:2], img[-2:], img[:, :2], img[:, -2:] = 0.2, 0.2, 0.2, 0.2
        img[..., 1][img[..., 0] == 0.2] = 0.4
        img[..., 2][img[..., 0] == 0.2] = 0.6
        write_png(path, img)
    from n2f2.gaussians.fit import border_color

    np.testing.assert_allclose(border_color(scene, list(range(9))), [51 / 255, 102 / 255, 153 / 255], atol=1e-6)
    cfg = replace(FitConfig.cpu(), steps=2, random_init_count=20, checkpoint_every=0, sh_degree=0)
    assert cfg.background_from_images
    fit_gaussians(scene, cfg, tmp_path / "fit", progress=False)
    saved = json.loads((tmp_path / "fit" / "fit_report.json").read_text())["config"]
    np.testing.assert_allclose(saved["background"], [51 / 255, 102 / 255, 153 / 255], atol=1e-6)
    assert saved["background_from_images"] is False  # resolved once; a resume keeps the colour


def test_environment_colour_over_ray_directions():
    from n2f2.gaussians.fit import Environment

    cam = _ring(1, 8, 6)[0]
    flat = Environment(0, (0.2, 0.4, 0.6))
    torch.testing.assert_close(flat(cam), torch.tensor([0.2, 0.4, 0.6]).expand(6, 8, 3))
    # Degree 1: Y_1,-1 = -0.488603 y for a unit direction (3DGS's basis); put 0.1 / 0.488603
    # there in red, so red = 0.2 - 0.1 y over the pixels' unit ray directions.
    env = Environment(1, (0.2, 0.4, 0.6))
    with torch.no_grad():
        env.sh[1, 0] = 0.1 / 0.4886025119029199
    dirs = cam.ray_directions()
    y = dirs[..., 1] / np.linalg.norm(dirs, axis=-1)
    np.testing.assert_allclose(env(cam)[..., 0].detach().numpy(), 0.2 - 0.1 * y, atol=1e-6)


def test_fit_learns_and_saves_the_environment(tmp_path):
    # Views of one flat colour and no Gaussians worth keeping: the environment takes the colour.
    scene = _scene(tmp_path / "scene", 9, 16, 12, colors=[(0.8, 0.3, 0.1)] * 9)
    cfg = replace(FitConfig.cpu(), steps=200, random_init_count=5, checkpoint_every=0, sh_degree=0,
                  background_from_images=False, background=(0.5, 0.5, 0.5), background_lr=0.05)
    assert cfg.background_sh_degree == 2
    report = fit_gaussians(scene, cfg, tmp_path / "fit", progress=False)
    saved = json.loads((tmp_path / "fit" / "background.json").read_text())
    assert saved["degree"] == 2 and len(saved["sh"]) == 9
    from n2f2.gaussians.fit import Environment

    env = Environment(2, (0.5, 0.5, 0.5))
    with torch.no_grad():
        env.sh.copy_(torch.tensor(saved["sh"]))
    seen = env(scene.cameras[0]).detach().numpy().reshape(-1, 3).mean(0)  # a held-out view
    np.testing.assert_allclose(seen, [0.8, 0.3, 0.1], atol=0.08)  # from grey 0.5: 0.2-0.4 away
    assert report.test_psnr > 20


# ------------------------------------------------------------------------------------ pruning
def test_prune_screen_size_removes_gaussians_that_covered_too_much_of_the_screen():
    n = 4
    g = Gaussians(torch.zeros(n, 3), torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n, 3), -3.0),
                  torch.full((n,), 2.0), torch.zeros(n, 1, 3))
    adam = GaussianAdam()
    stats = DensifyStats.zeros(n, "cpu")
    stats.max_radii = torch.tensor([0.05, 0.30, 0.0, 0.21])
    cfg = replace(FitConfig(), densify_grad_threshold=1.0, prune_screen_size=0.2)
    counts = densify_and_prune(g, adam, stats, cfg, 10.0, prune_big=False, generator=torch.Generator())
    assert counts["pruned"] == 2 and g.num == 2


# ------------------------------------------------------------------------------------ outputs
def test_fit_reports_step_times_and_writes_held_out_renders(tmp_path):
    scene = _scene(tmp_path / "scene", 9, 16, 12, colors=[(0.3, 0.5, 0.7)] * 9)
    cfg = replace(FitConfig.cpu(), steps=6, random_init_count=50, checkpoint_every=0, sh_degree=0,
                  test_every=8, densify_from=100)
    report = fit_gaussians(scene, cfg, tmp_path / "fit", progress=False)
    assert report.step_time_median_s is not None and report.step_time_p95_s >= report.step_time_median_s
    assert set(report.test_psnr_per_view) == {"frame_00001", "frame_00009"}
    assert np.mean(list(report.test_psnr_per_view.values())) == pytest.approx(report.test_psnr)
    render = np.load(tmp_path / "fit" / "test_views" / "frame_00001.npy")
    assert render.dtype == np.float32 and render.shape == (12, 16, 3)
    mse = float(((render - scene.image(0)) ** 2).mean())  # the photo as loaded (8-bit)
    assert -10 * math.log10(mse) == pytest.approx(report.test_psnr_per_view["frame_00001"], abs=0.05)
    assert (tmp_path / "fit" / "test_views" / "frame_00001.png").is_file()
    saved = json.loads((tmp_path / "fit" / "fit_report.json").read_text())
    assert saved["test_psnr_per_view"] == report.test_psnr_per_view


# ------------------------------------------------------------------------------------ orbit
def test_orbit_cameras_look_at_the_robust_centre_from_one_distance():
    rng = np.random.default_rng(0)
    n = 200
    means = torch.tensor(rng.normal(size=(n, 3)) * 0.1 + [1.0, 2.0, 3.0], dtype=torch.float32)
    means[0] = torch.tensor([50.0, 50.0, 50.0])  # a floater moves neither centre nor radius
    g = Gaussians(means, torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n, 3), -4.0),
                  torch.full((n,), 3.0), torch.zeros(n, 1, 3))
    cams = orbit_cameras(g, 6, elevation=30.0, up=(0.0, 0.0, 1.0), width=64, height=48)
    # The point closest to every optical axis (least squares) is the look-at point.
    A, b = np.zeros((3, 3)), np.zeros(3)
    for c in cams:
        P = np.eye(3) - np.outer(c.R[2], c.R[2])
        A, b = A + P, b + P @ c.center
    target = np.linalg.solve(A, b)
    assert np.linalg.norm(target - [1.0, 2.0, 3.0]) < 0.05  # the floater did not move it
    dists = [np.linalg.norm(c.center - target) for c in cams]
    assert max(dists) - min(dists) < 1e-9 and max(dists) < 5.0  # the floater did not push the ring out
    for c in cams:
        u, v = c.project(target[None])[0][0]
        assert abs(u - 32) < 1e-6 and abs(v - 24) < 1e-6
        rel = c.center - target
        assert math.degrees(math.asin(rel[2] / np.linalg.norm(rel))) == pytest.approx(30.0)


def test_render_command_draws_a_ply_in_its_colour(tmp_path):
    n = 50
    rng = np.random.default_rng(1)
    red = torch.zeros(n, 1, 3)
    red[:, 0] = (torch.tensor([1.0, 0.0, 0.0]) - 0.5) / 0.28209479177387814  # DC of pure red
    g = Gaussians(torch.tensor(rng.normal(size=(n, 3)) * 0.05, dtype=torch.float32),
                  torch.tensor([[1.0, 0, 0, 0]] * n), torch.full((n, 3), math.log(0.05)), torch.full((n,), 5.0),
                  red)
    write_ply(tmp_path / "g.ply", g)
    assert cli_main(["render", str(tmp_path / "g.ply"), "--out", str(tmp_path / "out"), "--views", "3",
                     "--size", "40", "30"]) == 0
    for k in range(3):
        img = np.load(tmp_path / "out" / f"orbit_{k:02d}.npy")
        assert img.shape == (30, 40, 3)
        np.testing.assert_allclose(img[15, 20], [1.0, 0.0, 0.0], atol=0.02)  # the centre is the red blob
        assert img[0, 0].min() > 0.5  # the white background at a corner (tinted by the blob's tail)
    assert render_views(g, orbit_cameras(g, 1, width=8, height=8))[0].dtype == np.float32


def test_render_command_rejects_bad_options(tmp_path, capsys):
    assert cli_main(["render", str(tmp_path / "missing.ply"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.ply" in capsys.readouterr().err
    with pytest.raises(SystemExit) as e:  # argparse's one-line error
        cli_main(["render", str(tmp_path / "x.ply"), "--out", str(tmp_path / "o"), "--views", "0"])
    assert e.value.code == 2 and "--views" in capsys.readouterr().err
