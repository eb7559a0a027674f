"""The built-in demo scene: determinism, hierarchy, exact depth, labels and queries."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from n2f2.data import labels as L
from n2f2.data.synthetic import (LEVELS, build_demo_scene, demo_cameras, generate_demo_scene,
                                 write_contact_sheet)
from n2f2.errors import InputError

NUM_VIEWS, WIDTH, HEIGHT, SEED = 8, 64, 48, 0
LABELLED = [1, 4, 6]


@pytest.fixture(scope="module")
def scene_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "scene"
    generate_demo_scene(out, num_views=NUM_VIEWS, width=WIDTH, height=HEIGHT, seed=SEED,
                        labelled_views=LABELLED, num_points=400, show_progress=False)
    return out


@pytest.fixture(scope="module")
def regions(scene_dir) -> dict:
    info = json.loads((scene_dir / "regions.json").read_text())
    return {r["id"]: r for r in info["regions"]}


def _region_stack(scene_dir: Path, view: int) -> np.ndarray:
    return np.load(scene_dir / "regions" / f"frame_{view + 1:05d}.npy")


# ----------------------------------------------------------------------------- layout
def test_layout(scene_dir):
    names = [f"frame_{i + 1:05d}" for i in range(NUM_VIEWS)]
    assert sorted(p.stem for p in (scene_dir / "images").glob("*.png")) == names
    for n in names:
        d = np.load(scene_dir / "depth" / f"{n}.npy")
        r = np.load(scene_dir / "regions" / f"{n}.npy")
        assert d.dtype == np.float32 and d.shape == (HEIGHT, WIDTH)
        assert r.dtype == np.int32 and r.shape == (3, HEIGHT, WIDTH)
        assert np.isfinite(d).all() and (d > 0).all()
    for f in ("transforms.json", "sparse/0/cameras.txt", "sparse/0/images.txt",
              "sparse/0/points3D.txt", "queries.json", "regions.json", "points_source.npy"):
        assert (scene_dir / f).is_file(), f
    meta = json.loads((scene_dir / "scene.json").read_text())
    assert meta["seed"] == SEED and meta["num_views"] == NUM_VIEWS
    assert meta["width"] == WIDTH and meta["height"] == HEIGHT
    assert meta["test_views"] == [0]  # every 8th view
    assert meta["labelled_views"] == LABELLED
    assert sorted(p.stem for p in (scene_dir / "label").glob("*.json")) == \
        [f"frame_{v + 1:05d}" for v in LABELLED]
    info = json.loads((scene_dir / "regions.json").read_text())
    assert info["levels"] == ["part", "object", "group"] == list(LEVELS)


# ----------------------------------------------------------------------------- determinism
def test_deterministic_for_a_seed(scene_dir, tmp_path):
    again = generate_demo_scene(tmp_path / "again", num_views=NUM_VIEWS, width=WIDTH, height=HEIGHT,
                                seed=SEED, labelled_views=LABELLED, num_points=400,
                                show_progress=False)
    files = sorted(p.relative_to(scene_dir) for p in scene_dir.rglob("*") if p.is_file())
    assert files == sorted(p.relative_to(again) for p in again.rglob("*") if p.is_file())
    assert len(files) > 4 * NUM_VIEWS
    for rel in files:  # every file, images and region ids included, byte for byte
        assert (again / rel).read_bytes() == (scene_dir / rel).read_bytes(), rel
    other = generate_demo_scene(tmp_path / "other", num_views=2, width=WIDTH, height=HEIGHT,
                                seed=SEED + 1, num_points=50, show_progress=False)
    first = generate_demo_scene(tmp_path / "first", num_views=2, width=WIDTH, height=HEIGHT,
                                seed=SEED, num_points=50, show_progress=False)
    assert (other / "images/frame_00001.png").read_bytes() != (first / "images/frame_00001.png").read_bytes()


# ----------------------------------------------------------------------------- hierarchy
def test_region_table(regions):
    assert len(regions) == len({r["id"] for r in regions.values()})
    for r in regions.values():
        assert r["level"] in (0, 1, 2)
        assert isinstance(r["caption"], str) and len(r["caption"].split()) >= 1
        if r["level"] == 2:
            assert r["parent"] is None
        else:
            assert regions[r["parent"]]["level"] == r["level"] + 1
    captions = {r["caption"] for r in regions.values()}
    for needed in ("the lid of the teapot", "a red mug", "a bag of cookies", "loose cookies",
                   "a plate of fruit", "the handle of the blue mug"):
        assert needed in captions
    by_name = {r["name"]: r for r in regions.values()}
    # two mugs share a noun; only the blue one has parts
    kids = lambda rid: [r for r in regions.values() if r["parent"] == rid]  # noqa: E731
    assert kids(by_name["red mug"]["id"]) == []
    assert {r["name"] for r in kids(by_name["blue mug"]["id"])} == {"blue mug body", "blue mug handle"}
    assert {r["name"] for r in kids(by_name["teapot"]["id"])} >= {"teapot lid", "teapot spout",
                                                                   "teapot handle"}


def test_pixels_follow_the_hierarchy(scene_dir, regions):
    has_parts = {r["parent"] for r in regions.values() if r["level"] == 0}
    for v in range(NUM_VIEWS):
        part, obj, group = _region_stack(scene_dir, v)
        assert (obj >= 0).all() and (group >= 0).all(), "floor and walls are labelled objects"
        for level, layer in enumerate((part, obj, group)):
            for rid in np.unique(layer[layer >= 0]):
                assert regions[int(rid)]["level"] == level
        # every part pixel's object is the part's parent, every object pixel's group its parent
        parent_of = np.full(max(regions) + 1, -1)
        for r in regions.values():
            parent_of[r["id"]] = -1 if r["parent"] is None else r["parent"]
        sel = part >= 0
        assert (parent_of[part[sel]] == obj[sel]).all()
        assert (parent_of[obj] == group).all()
        # objects with parts are fully covered by their parts; objects without have part -1
        obj_has_parts = np.isin(obj, list(has_parts))
        assert (sel == obj_has_parts).all()


def test_tabletop_objects_are_visible(scene_dir, regions):
    seen = set()
    for v in range(NUM_VIEWS):
        r = _region_stack(scene_dir, v)
        seen |= {int(x) for x in np.unique(r) if x >= 0}
    # every region, including the small parts, shows up in some view
    assert seen == set(regions)


# ----------------------------------------------------------------------------- exact depth
def _boundary_distance(prim, points: np.ndarray) -> np.ndarray:
    """Distance-like residual [N] of points [N, 3] to the primitive's boundary, written
    from the shape definitions (independent of the ray-intersection code)."""
    p = (points - prim.center) @ prim.rotation
    s = np.asarray(prim.size, dtype=np.float64)
    tol = 1e-6
    if prim.kind == "plane":
        return np.abs(p[:, 2])
    if prim.kind == "ellipsoid":
        return np.abs(np.linalg.norm(p / s, axis=1) - 1.0) * s.min()
    if prim.kind == "box":
        best = np.full(len(p), np.inf)
        for a in range(3):
            others = [b for b in range(3) if b != a]
            inside = (np.abs(p[:, others]) <= s[others] + tol).all(1)
            face = np.abs(np.abs(p[:, a]) - s[a])
            best = np.minimum(best, np.where(inside, face, np.inf))
        return best
    rb, rt, hh = (s[0], s[0], s[1]) if prim.kind == "cylinder" else s
    rho = np.hypot(p[:, 0], p[:, 1])
    r_at_z = rb + (rt - rb) * (p[:, 2] + hh) / (2 * hh)
    side = np.where(np.abs(p[:, 2]) <= hh + tol, np.abs(rho - r_at_z), np.inf)
    bottom = np.where(rho <= rb + tol, np.abs(p[:, 2] + hh), np.inf)
    top = np.where(rho <= rt + tol, np.abs(p[:, 2] - hh), np.inf)
    return np.minimum(side, np.minimum(bottom, top))


def test_depth_lies_on_the_labelled_primitive(scene_dir):
    scene = build_demo_scene(SEED)
    cams = demo_cameras(NUM_VIEWS, WIDTH, HEIGHT, SEED)
    worst = 0.0
    for v in (0, 3, 5):
        depth = np.load(scene_dir / "depth" / f"frame_{v + 1:05d}.npy").astype(np.float64)
        part, obj, _ = _region_stack(scene_dir, v)
        rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
        uv = np.stack([cols + 0.5, rows + 0.5], -1).reshape(-1, 2)
        pts = cams[v].unproject(uv, depth.reshape(-1))
        finest = np.where(part >= 0, part, obj).reshape(-1)
        dist = np.full(len(pts), np.inf)
        for prim in scene.primitives:
            owner = prim.part if prim.part >= 0 else prim.object
            sel = finest == owner
            if sel.any():
                dist[sel] = np.minimum(dist[sel], _boundary_distance(prim, pts[sel]))
        worst = max(worst, float(dist.max()))
    # float32 depth of ~1-4 m: about 3e-7 m of rounding
    assert worst < 2e-5, worst


def test_depth_is_z_depth_of_a_hand_checked_pixel():
    """Known answer by hand: a camera straight above the table centre sees the tabletop cloth
    at z-depth = camera height - 0.75 for a pixel whose ray misses everything on the table."""
    from n2f2.cameras import Camera, look_at
    from n2f2.data.synthetic import render_view

    scene = build_demo_scene(SEED)
    R, t = look_at((0.0, 0.0, 2.0), (0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0))
    cam = Camera(40.0, 40.0, 16.0, 16.0, 32, 32, R=R, t=t)
    view = render_view(scene, cam, supersample=1)
    # nothing stands at the table centre: the pixel next to the optical axis sees the cloth
    assert view.regions[0, 16, 16] == scene.region("tabletop").id
    on_cloth = view.regions[0] == scene.region("tabletop").id
    assert on_cloth.sum() > 50
    np.testing.assert_allclose(view.depth[on_cloth], 2.0 - 0.75, atol=1e-9)
    # rays through the corners miss the table (radius 0.62 < 1.25 * 16 / 40 * sqrt 2) and hit
    # the floor at z-depth 2.0
    assert view.regions[1, 0, 0] == scene.region("floor").id
    np.testing.assert_allclose(view.depth[0, 0], 2.0, atol=1e-9)


# ----------------------------------------------------------------------------- labels
def _gt_mask(stack: np.ndarray, regions: dict, ids) -> np.ndarray:
    m = np.zeros(stack.shape[1:], dtype=bool)
    for rid in ids:
        m |= stack[regions[rid]["level"]] == rid
    return m


def test_labels_match_the_ground_truth_masks(scene_dir, regions):
    queries = json.loads((scene_dir / "queries.json").read_text())["queries"]
    frames = L.read_label_dir(scene_dir / "label")
    assert [f.view_index for f in frames] == LABELLED
    checked = 0
    for f in frames:
        assert (f.height, f.width) == (HEIGHT, WIDTH)
        stack = _region_stack(scene_dir, f.view_index)
        for q in queries:
            gt = _gt_mask(stack, regions, q["region_ids"])
            got = f.mask(q["query"])
            if gt.sum() >= 4:
                assert q["query"] in f.categories
            if gt.sum() >= 20:
                iou = (gt & got).sum() / (gt | got).sum()
                assert iou >= 0.9, (f.frame_name, q["query"], iou)
                checked += 1
            for box, obj in zip(f.bboxes(q["query"]), [o for o in f.objects if o.category == q["query"]]):
                poly = np.asarray(obj.polygon)
                assert box[0] == poly[:, 0].min() and box[3] == poly[:, 1].max()
    assert checked >= 20


def test_repeated_category_for_separate_pieces():
    mask = np.zeros((30, 40), dtype=bool)
    mask[2:8, 3:9] = True
    mask[15:25, 20:35] = True
    mask[18:22, 24:28] = False  # a hole
    fl = L.labels_from_masks("frame_00007", {"cookies": mask})
    assert [o.category for o in fl.objects] == ["cookies", "cookies"]
    assert fl.view_index == 6
    assert (fl.mask("cookies") == mask).all()  # holes survive the polygon format
    boxes = sorted(map(tuple, fl.bboxes("cookies")))
    assert boxes == [(3, 2, 8, 7), (20, 15, 34, 24)]


def test_label_file_round_trip(tmp_path):
    fl = L.FrameLabels("frame_00012", 48, 64, [
        L.LabelObject("red mug", (1.0, 2.0, 10.0, 12.0), [[1, 2], [10, 2], [10, 12], [1, 12]]),
        L.LabelObject("red mug", (20.5, 3.0, 30.0, 9.0), [[20.5, 3], [30, 3], [30, 9]]),
    ])
    L.write_frame_labels(tmp_path / "frame_00012.json", fl)
    raw = json.loads((tmp_path / "frame_00012.json").read_text())
    assert raw["info"] == {"name": "frame_00012.jpg", "height": 48, "width": 64}
    assert raw["objects"][0] == {"category": "red mug", "bbox": [1, 2, 10, 12],
                                 "segmentation": [[1, 2], [10, 2], [10, 12], [1, 12]]}
    back = L.read_label_dir(tmp_path)
    assert len(back) == 1 and back[0].view_index == 11
    assert back[0].objects[1].polygon == [[20.5, 3.0], [30.0, 3.0], [30.0, 9.0]]
    assert back[0].mask("red mug")[2:13, 1:11].all()


@pytest.mark.parametrize("content, problem", [
    ("{not json", "not valid JSON"),
    ('{"objects": []}', "info"),
    ('{"info": {"name": "a.jpg", "height": 4}, "objects": []}', "width"),
    ('{"info": {"name": "a.jpg", "height": 4, "width": "5"}, "objects": []}', "width"),
    ('{"info": {"name": "a.jpg", "height": 4, "width": 5}}', "objects"),
    ('{"info": {"height": 4, "width": 5}, "objects": [{"bbox": [0,0,1,1], "segmentation": [[0,0]]}]}',
     "category"),
    ('{"info": {"height": 4, "width": 5}, "objects": [{"category": "x", "bbox": [0,0,1], '
     '"segmentation": [[0,0]]}]}', "bbox"),
    ('{"info": {"height": 4, "width": 5}, "objects": [{"category": "x", "bbox": [0,0,1,1], '
     '"segmentation": [[0,"a"]]}]}', "segmentation"),
    ('[]', "JSON object"),
])
def test_bad_label_files_name_the_file(tmp_path, content, problem):
    (tmp_path / "frame_00001.json").write_text(content)
    with pytest.raises(InputError) as e:
        L.read_label_dir(tmp_path)
    assert "frame_00001.json" in str(e.value) and problem in str(e.value)


def test_empty_or_badly_named_label_folder(tmp_path):
    with pytest.raises(InputError, match="no frame_XXXXX.json"):
        L.read_label_dir(tmp_path)
    with pytest.raises(InputError, match="does not exist"):
        L.read_label_dir(tmp_path / "missing")
    (tmp_path / "frame_00000.json").write_text('{"info": {"height": 1, "width": 1}, "objects": []}')
    with pytest.raises(InputError, match="numbered from 1"):
        L.read_label_dir(tmp_path)


# ----------------------------------------------------------------------------- queries, extents
def test_queries_reference_existing_regions(scene_dir, regions):
    queries = json.loads((scene_dir / "queries.json").read_text())["queries"]
    assert 12 <= len(queries) <= 24
    assert {q["type"] for q in queries} == {"simple", "compound"}
    levels = set()
    for q in queries:
        assert q["region_ids"] and all(rid in regions for rid in q["region_ids"])
        levels |= {regions[rid]["level"] for rid in q["region_ids"]}
    assert levels == {0, 1, 2}
    by_query = {q["query"]: q for q in queries}
    for compound in ("lid of the teapot", "red mug", "bag of cookies", "handle of the blue mug",
                     "plate of fruit"):
        assert by_query[compound]["type"] == "compound"
    for simple in ("teapot", "plate", "cookies"):
        assert by_query[simple]["type"] == "simple"
    # "mug" covers both mugs; "red mug" only one of them
    assert set(by_query["red mug"]["region_ids"]) < set(by_query["mug"]["region_ids"])


def test_extents_nest_and_bound_each_other(regions):
    for r in regions.values():
        assert r["extent"] == r["extent_diag"] and r["extent_diag"] > 0
        # the standard deviation along the principal axis is at most half the bbox diagonal
        assert np.sqrt(r["extent_eig"]) <= 0.5 * r["extent_diag"] + 1e-9
        if r["parent"] is not None:  # a child's points are a subset of its parent's
            assert r["extent_diag"] <= regions[r["parent"]]["extent_diag"] + 1e-9
    by_name = {r["name"]: r for r in regions.values()}
    # known sizes: the lid (radius 0.062 + knob) is well under 0.2 m, the teapot over 0.25 m
    assert by_name["teapot lid"]["extent_diag"] < 0.2
    assert by_name["teapot"]["extent_diag"] > 0.25
    assert by_name["wall"]["extent_diag"] > 2.0


def test_regenerating_replaces_only_a_demo_scene(tmp_path):
    out = generate_demo_scene(tmp_path / "s", num_views=3, width=16, height=12, num_points=10,
                              labelled_views=[2], show_progress=False)
    generate_demo_scene(out, num_views=2, width=16, height=12, num_points=10,
                        labelled_views=[0], show_progress=False)
    assert sorted(p.name for p in (out / "images").iterdir()) == ["frame_00001.png", "frame_00002.png"]
    assert sorted(p.name for p in (out / "label").glob("*.json")) == ["frame_00001.json"]
    other = tmp_path / "mine"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(InputError, match="not empty"):
        generate_demo_scene(other, num_views=1, width=16, height=12, show_progress=False)
    assert (other / "notes.txt").read_text() == "keep me"


def test_contact_sheet(scene_dir, tmp_path):
    from PIL import Image

    out = write_contact_sheet(scene_dir, tmp_path / "sheet.png", max_views=3)
    with Image.open(out) as im:
        assert im.size[0] > im.size[1] > 100


# ----------------------------------------------------------------------------- the default layout
# The fixture's tabletop scene as the generator wrote it before layouts existed: the default
# layout must keep rendering that scene (the demo numbers depend on it). Depth, region ids, point
# sources, region table and queries are pinned bit for bit (TABLETOP_GEOMETRY_DIGEST). The
# pixels are compared with tests/data/tabletop_fixture_images.npz: their shading goes through
# NumPy's matrix products, whose BLAS kernel (OpenBLAS picks one per CPU) rounds differently, and
# near a shadow's edge that moves a pixel by up to 25 levels (83 of these 24,576 differ between
# OpenBLAS's Haswell and SkylakeX kernels); a changed scene moves far more.
TABLETOP_GEOMETRY_DIGEST = "e3e1a6c4ee2a2790bfeaca2f1cdb4f6b31e8cce098614a1c8ddfe45fbe57adea"
IMAGES_REFERENCE = Path(__file__).parent / "data" / "tabletop_fixture_images.npz"
MAX_CHANGED_PIXELS = 0.01  # fraction of the fixture's pixels allowed to differ from the reference


def _geometry_digest(scene_dir: Path) -> str:
    import hashlib

    h = hashlib.sha256()
    for img in sorted((scene_dir / "images").glob("*.png")):
        for sub in ("depth", "regions"):
            h.update(np.load(scene_dir / sub / f"{img.stem}.npy").tobytes())
    h.update(np.load(scene_dir / "points_source.npy").tobytes())
    regions = json.loads((scene_dir / "regions.json").read_text())["regions"]
    table = [[r["id"], r["level"], r["name"], r["caption"], r["parent"]] for r in regions]
    h.update(json.dumps(table).encode())
    h.update(json.dumps(json.loads((scene_dir / "queries.json").read_text()), sort_keys=True).encode())
    return h.hexdigest()


def test_default_layout_is_the_tabletop_unchanged(scene_dir):
    from PIL import Image

    assert json.loads((scene_dir / "scene.json").read_text())["layout"] == "tabletop"
    assert _geometry_digest(scene_dir) == TABLETOP_GEOMETRY_DIGEST
    images = []
    for img in sorted((scene_dir / "images").glob("*.png")):
        with Image.open(img) as im:
            images.append(np.asarray(im.convert("RGB")))
    with np.load(IMAGES_REFERENCE) as ref:
        expected = ref["images"]  # [views, H, W, 3] uint8
    got = np.stack(images)
    assert got.shape == expected.shape == (NUM_VIEWS, HEIGHT, WIDTH, 3)
    changed = (got != expected).any(axis=-1)  # [views, H, W]
    assert changed.mean() <= MAX_CHANGED_PIXELS


# ----------------------------------------------------------------------------- the lounge layout
@pytest.fixture(scope="module")
def lounge_dir(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("lounge") / "scene"
    # a tabletop there first: a lounge generation replaces another layout's demo scene
    generate_demo_scene(out, num_views=2, width=16, height=12, num_points=10, labelled_views=[1],
                        show_progress=False)
    generate_demo_scene(out, num_views=NUM_VIEWS, width=WIDTH, height=HEIGHT, seed=SEED,
                        labelled_views=LABELLED, num_points=400, show_progress=False, layout="lounge")
    return out


@pytest.fixture(scope="module")
def lounge_regions(lounge_dir) -> dict:
    info = json.loads((lounge_dir / "regions.json").read_text())
    assert info["levels"] == list(LEVELS)
    return {r["id"]: r for r in info["regions"]}


def test_lounge_files(lounge_dir):
    meta = json.loads((lounge_dir / "scene.json").read_text())
    assert meta["layout"] == "lounge" and meta["num_views"] == NUM_VIEWS
    assert sorted(p.name for p in (lounge_dir / "images").iterdir()) == \
        [f"frame_{i + 1:05d}.png" for i in range(NUM_VIEWS)]
    for i in range(NUM_VIEWS):
        d = np.load(lounge_dir / "depth" / f"frame_{i + 1:05d}.npy")
        assert d.shape == (HEIGHT, WIDTH) and np.isfinite(d).all() and (d > 0).all()
    assert sorted(p.stem for p in (lounge_dir / "label").glob("*.json")) == \
        [f"frame_{v + 1:05d}" for v in LABELLED]
    lines = [ln for ln in (lounge_dir / "sparse/0/points3D.txt").read_text().splitlines()
             if ln and not ln.startswith("#")]
    assert len(lines) == 400


def test_lounge_is_a_different_scene(lounge_regions, regions):
    names = {r["name"] for r in lounge_regions.values()}
    # only the room's floor and walls share a name with the tabletop
    assert names & {r["name"] for r in regions.values()} == {"room", "floor", "wall"}
    captions = {r["caption"] for r in lounge_regions.values()}
    for needed in ("the shade of the lamp", "the flowers in the vase", "a bowl of fruit",
                   "the wheels of the toy car", "a stack of books", "a yellow cushion"):
        assert needed in captions
    assert sum(r["level"] == 2 for r in lounge_regions.values()) == 3


def test_lounge_hierarchy(lounge_dir, lounge_regions):
    regions = lounge_regions
    assert len({r["name"] for r in regions.values()}) == len(regions)
    parent_of = np.full(max(regions) + 1, -1)
    for r in regions.values():
        assert isinstance(r["caption"], str) and r["caption"]
        if r["level"] == 2:
            assert r["parent"] is None
        else:
            assert regions[r["parent"]]["level"] == r["level"] + 1
            parent_of[r["id"]] = r["parent"]
    has_parts = {r["parent"] for r in regions.values() if r["level"] == 0}
    for v in range(NUM_VIEWS):
        part, obj, group = _region_stack(lounge_dir, v)
        assert (obj >= 0).all() and (group >= 0).all()
        for level, layer in enumerate((part, obj, group)):
            assert all(regions[int(rid)]["level"] == level for rid in np.unique(layer[layer >= 0]))
        sel = part >= 0
        assert (parent_of[part[sel]] == obj[sel]).all()
        assert (parent_of[obj] == group).all()
        assert (sel == np.isin(obj, list(has_parts))).all()


def test_lounge_depth_lies_on_the_labelled_primitive(lounge_dir):
    scene = build_demo_scene(SEED, layout="lounge")
    cams = demo_cameras(NUM_VIEWS, WIDTH, HEIGHT, SEED, layout="lounge")
    worst = 0.0
    for v in range(NUM_VIEWS):
        depth = np.load(lounge_dir / "depth" / f"frame_{v + 1:05d}.npy").astype(np.float64)
        part, obj, _ = _region_stack(lounge_dir, v)
        rows, cols = np.mgrid[0:HEIGHT, 0:WIDTH]
        uv = np.stack([cols + 0.5, rows + 0.5], -1).reshape(-1, 2)
        pts = cams[v].unproject(uv, depth.reshape(-1))
        finest = np.where(part >= 0, part, obj).reshape(-1)
        dist = np.full(len(pts), np.inf)
        for prim in scene.primitives:
            owner = prim.part if prim.part >= 0 else prim.object
            sel = finest == owner
            if sel.any():
                dist[sel] = np.minimum(dist[sel], _boundary_distance(prim, pts[sel]))
        worst = max(worst, float(dist.max()))
    assert worst < 5e-5, worst  # float32 depth of up to ~10 m: about 1e-6 m of rounding


def test_lounge_queries_and_labels(lounge_dir, lounge_regions):
    queries = json.loads((lounge_dir / "queries.json").read_text())["queries"]
    assert 12 <= len(queries) <= 24
    assert {q["type"] for q in queries} == {"simple", "compound"}
    assert len({q["query"] for q in queries}) == len(queries)
    levels = set()
    for q in queries:
        assert q["region_ids"] and all(rid in lounge_regions for rid in q["region_ids"])
        levels |= {lounge_regions[rid]["level"] for rid in q["region_ids"]}
    assert levels == {0, 1, 2}
    by_query = {q["query"]: q for q in queries}
    name = {r["id"]: r["name"] for r in lounge_regions.values()}
    assert {name[i] for i in by_query["book"]["region_ids"]} == {"red book", "green book", "blue book"}
    assert set(by_query["yellow cushion"]["region_ids"]) < set(by_query["cushion"]["region_ids"])
    assert by_query["shade of the lamp"]["type"] == "compound" and by_query["sofa"]["type"] == "simple"
    checked = 0
    for f in L.read_label_dir(lounge_dir / "label"):
        stack = _region_stack(lounge_dir, f.view_index)
        for q in queries:
            gt = _gt_mask(stack, lounge_regions, q["region_ids"])
            if gt.sum() >= 20:
                iou = (gt & f.mask(q["query"])).sum() / (gt | f.mask(q["query"])).sum()
                assert iou >= 0.9, (f.frame_name, q["query"], iou)
                checked += 1
    assert checked >= 20


def test_lounge_walls_are_farther(lounge_dir, lounge_regions, scene_dir, regions):
    """The lounge's walls are at x = +-7, y = +-5.5 m (the tabletop's at +-3 m), so its wall
    pixels are about twice as deep."""
    def wall_depths(folder, table):
        wall = next(r["id"] for r in table.values() if r["name"] == "wall")
        return np.concatenate([np.load(folder / "depth" / f"frame_{v + 1:05d}.npy")[
            _region_stack(folder, v)[1] == wall] for v in range(NUM_VIEWS)])

    lounge, tabletop = wall_depths(lounge_dir, lounge_regions), wall_depths(scene_dir, regions)
    assert len(lounge) > 0.2 * NUM_VIEWS * WIDTH * HEIGHT and len(tabletop) > 0
    assert np.median(lounge) > 1.6 * np.median(tabletop), (np.median(lounge), np.median(tabletop))


def test_lounge_camera_path():
    """A partial arc, lower than the tabletop's ring, with some views close to the table."""
    n = 40
    lounge = np.stack([c.center for c in demo_cameras(n, WIDTH, HEIGHT, SEED, layout="lounge")])
    ring = np.stack([c.center for c in demo_cameras(n, WIDTH, HEIGHT, SEED)])
    azimuth = np.sort(np.arctan2(lounge[:, 1], lounge[:, 0]))
    gaps = np.diff(np.concatenate([azimuth, azimuth[:1] + 2 * np.pi]))
    assert gaps.max() > np.radians(120)  # the ring's largest gap is about 9 degrees
    assert np.median(lounge[:, 2]) < np.median(ring[:, 2]) - 0.3
    assert np.ptp(lounge[:, 2]) > 0.4
    # distance from the eye to the nearest point of the coffee table top (1.2 x 0.7 m, z 0.425)
    nearest = np.stack([np.clip(lounge[:, 0], -0.6, 0.6), np.clip(lounge[:, 1], -0.35, 0.35),
                        np.full(n, 0.425)], 1)
    gap = np.linalg.norm(lounge - nearest, axis=1)
    assert 3 <= (gap < 0.6).sum() <= n // 3 and (gap > 0.2).all()


def test_unknown_layout():
    with pytest.raises(ValueError, match="lounge"):
        build_demo_scene(SEED, layout="attic")
    with pytest.raises(ValueError, match="layout"):
        demo_cameras(2, 16, 12, layout="attic")


def test_demo_command_layout_is_part_of_the_cache_key(tmp_path, capsys):
    from n2f2.cli import main

    argv = ["demo", "--scene-only", "--out", str(tmp_path), "--views", "2", "--width", "16",
            "--height", "12", "--quiet"]
    assert main([*argv, "--layout", "lounge"]) == 0
    assert json.loads((tmp_path / "scene/scene.json").read_text())["layout"] == "lounge"
    assert main([*argv, "--layout", "lounge"]) == 0
    assert "up to date" in capsys.readouterr().out
    assert main(argv) == 0  # the default layout: regenerated
    assert json.loads((tmp_path / "scene/scene.json").read_text())["layout"] == "tabletop"
    assert (tmp_path / "contact_sheet.png").is_file()
