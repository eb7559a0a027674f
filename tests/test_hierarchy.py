"""``n2f2 decompose``: the hierarchy of a field with known clusters is the known tree, nesting
holds by construction, per-view node id maps equal a brute-force render, the PLY round trip keeps
the node properties, and a run without a field is refused with one line."""

from __future__ import annotations

import json
import shutil
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from n2f2.field.variants import VARIANTS
from n2f2.hierarchy.build import DecomposeConfig, choose_levels, decompose


def _known_field(per_part: int = 20, noise: float = 0.01, seed: int = 0):
    """A nested field of D = 8, k = 2 (prefixes 2, 4, 6, 8) with W = I: at prefix 2 three groups
    (directions 120 degrees apart), at prefix 4 two objects per group, at prefix 6 two parts per
    object, and nothing more at prefix 8. Each part is a blob of radius 0.1 around its own point
    of a 1-unit grid. Returns theta [N, 8], the centres [N, 3], W [8, 8] and the true labels of
    each Gaussian per level (group, object, part)."""
    g = torch.Generator().manual_seed(seed)
    rows, labels, centres = [], [], []
    for grp in range(3):
        angle = 2 * np.pi * grp / 3
        for obj in range(2):
            for part in range(2):
                t = torch.zeros(per_part, 8)
                t[:, 0], t[:, 1] = float(np.cos(angle)), float(np.sin(angle))
                t[:, 2 + obj] = 1.0  # the object's own direction at prefix 4
                t[:, 4 + part] = 1.0  # the part's at prefix 6
                rows.append(t + noise * torch.randn(per_part, 8, generator=g))
                labels += [(grp, 2 * grp + obj, 4 * grp + 2 * obj + part)] * per_part
                spot = torch.tensor([float(grp), float(obj), float(part)])
                centres.append(spot + 0.1 * torch.randn(per_part, 3, generator=g))
    return torch.cat(rows), torch.cat(centres), torch.eye(8), np.array(labels)


def _same_partition(a: np.ndarray, b: np.ndarray) -> bool:
    """Whether labelings ``a`` and ``b`` [N] group the items alike (up to renaming)."""
    pairs = set(zip(a.tolist(), b.tolist()))
    return len(pairs) == len(set(a.tolist())) == len(set(b.tolist()))


def test_a_field_with_known_clusters_gives_the_known_tree():
    theta, means, W, truth = _known_field()
    dec = decompose(theta, means, W, VARIANTS["nested"], 2, DecomposeConfig())
    assert dec.level_labels == ["d=2", "d=4", "d=8"]  # d=6 groups as d=8 does: the finer one is kept
    assert [int((dec.levels == lv).sum()) for lv in range(3)] == [3, 6, 12]
    for level in range(3):
        assert _same_partition(dec.gaussian_nodes[:, level], truth[:, level]), level
    # Nesting: every node's Gaussians lie in its parent; ids are global, coarsest level first.
    for level in range(1, 3):
        child, parent = dec.gaussian_nodes[:, level], dec.gaussian_nodes[:, level - 1]
        assert (dec.parents[child] == parent).all()
    assert (dec.parents[dec.levels == 0] == -1).all()
    assert sorted(np.unique(dec.gaussian_nodes).tolist()) == list(range(dec.num_nodes))


def test_nesting_holds_by_construction_on_noise():
    """A field of pure noise still gives a tree whose every node lies in one parent."""
    g = torch.Generator().manual_seed(1)
    theta = torch.randn(600, 16, generator=g)
    means = torch.randn(600, 3, generator=g)
    W = torch.randn(12, 16, generator=g)
    dec = decompose(theta, means, W, VARIANTS["nested"], 1, DecomposeConfig(max_levels=6))
    assert 1 <= dec.num_levels <= 6
    for level in range(1, dec.num_levels):
        child, parent = dec.gaussian_nodes[:, level], dec.gaussian_nodes[:, level - 1]
        for node in np.unique(child):
            assert len(np.unique(parent[child == node])) == 1


def test_the_levels_are_where_the_grouping_changes_most():
    # Node counts of 7 candidates, coarse to fine (nested, so equal counts are equal groupings).
    counts = [1, 3, 3, 6, 7, 24, 25]
    # Distinct groupings: indices 0, 2, 3, 4, 5, 6; the single node goes; growth over the next
    # coarser kept one: 3 (idx 2, from 1), 2 (3), 7/6 (4), 24/7 (5), 25/24 (6).
    assert choose_levels(counts, 6) == [2, 3, 4, 5, 6]
    assert choose_levels(counts, 2) == [2, 5]
    assert choose_levels([1, 1], 6) == [1]


def test_levels_field_is_coarse_first():
    levels = VARIANTS["levels"]
    assert levels.coarse_to_fine_labels(12) == ["group", "object", "part"]
    assert levels.coarse_to_fine(12) == [(0, 4), (4, 8), (8, 12)]
    assert VARIANTS["nested"].coarse_to_fine_values(12, 3) == [0.875, 0.625, 0.375, 0.125]


def test_node_id_maps_equal_a_brute_force_render():
    from n2f2.hierarchy.views import node_id_maps, node_id_maps_reference
    from n2f2.render.reference import rasterize_reference, random_scene

    (means, quats, scales, opac, _), cam = random_scene(400, 24, 1, seed=3)
    g = SimpleNamespace(means=means, quats=quats, scales=scales, opacities=opac)
    rng = np.random.default_rng(0)
    coarse = rng.integers(0, 5, size=400)
    nodes = np.stack([coarse, 5 + 3 * coarse + rng.integers(0, 3, size=400)], axis=1)  # 5 + 15 nodes
    fast = node_id_maps(g, nodes, cam, channels=4)  # several passes of 4 channels
    ref = node_id_maps_reference(g, nodes, cam)
    assert fast.shape == ref.shape == (2, 24, 24) and fast.dtype == np.int32
    for level in range(2):
        # Pixels whose two best nodes are within float rounding of each other may go either way.
        ids = torch.from_numpy(nodes[:, level])
        uniq = torch.unique(ids)
        cov = rasterize_reference(means, quats, scales, opac, (ids[:, None] == uniq[None]).float(), cam).features
        top2 = cov.topk(2, dim=-1).values
        clear = (top2[..., 0] - top2[..., 1] > 1e-4).numpy()
        assert clear.mean() > 0.9
        assert (fast[level][clear] == ref[level][clear]).all()
        assert set(np.unique(ref[level])) <= set(uniq.tolist()) | {-1}


@pytest.fixture(scope="module")
def demo_run(trained_run):
    return trained_run.run_dir


@pytest.fixture(scope="module")
def decomposed(trained_run, tmp_path_factory):
    """The shared demo run decomposed with two views and a vocabulary."""
    from n2f2.cli import main

    out = tmp_path_factory.mktemp("decomposition")
    vocab = out.parent / "vocab.txt"
    vocab.write_text("teapot\n# a comment\n\nlid of the teapot\nbag of cookies\n")
    assert main(["decompose", str(trained_run.run_dir), "--out", str(out), "--vocabulary", str(vocab),
                 "--views", "frame_00001", "frame_00002", "--quiet"]) == 0
    return out, trained_run.scene_dir


def test_the_folder_holds_a_consistent_tree(decomposed, demo_run):
    from n2f2.gaussians import read_ply
    from n2f2.hierarchy.files import read_ply_nodes, read_tree

    out, _ = decomposed
    n = read_ply(demo_run / "gaussians.ply").num
    tree = read_tree(out, num_gaussians=n)
    assert tree.gaussian_nodes.shape == (n, tree.num_levels) and 1 <= tree.num_levels <= 6
    nodes = tree.tree["nodes"]
    for k, rec in enumerate(nodes):
        assert rec["id"] == k and rec["gaussians"] == int((tree.gaussian_nodes[:, rec["level"]] == k).sum())
        for level in range(rec["level"], rec["last_level"] + 1):  # the same Gaussians over its span
            assert rec["gaussians"] == int((tree.gaussian_nodes[:, level] == k).sum())
        assert rec["text"] in ("teapot", "lid of the teapot", "bag of cookies") and 0 < rec["relevancy"] < 1
        lo, hi = np.array(rec["box"])
        assert (lo <= np.array(rec["centroid"])).all() and (np.array(rec["centroid"]) <= hi).all()
    assert tree.tree["settings"]["seed"] == 0 and tree.tree["settings"]["max_levels"] == 6
    # The PLY round trip keeps the node properties, coarsest first.
    assert (read_ply_nodes(out / "decomposition.ply") == tree.gaussian_nodes).all()
    assert read_ply(out / "decomposition.ply").num == n  # still an INRIA-layout PLY


def test_the_views_equal_a_render_of_the_node_ids(decomposed, demo_run):
    from n2f2.data import load_scene
    from n2f2.gaussians import read_ply
    from n2f2.hierarchy.files import read_tree
    from n2f2.hierarchy.views import node_id_maps

    out, scene_dir = decomposed
    levels = np.load(out / "views" / "frame_00002" / "levels.npy")
    scene = load_scene(scene_dir)
    g = read_ply(demo_run / "gaussians.ply")
    tree = read_tree(out)
    assert levels.shape == (tree.num_levels, scene.cameras[1].height, scene.cameras[1].width)
    assert (levels == node_id_maps(g, tree.gaussian_nodes, scene.cameras[1])).all()
    for level in range(tree.num_levels):  # the ids shown at a level are that level's nodes
        shown = set(np.unique(levels[level]).tolist()) - {-1}
        here = (tree.levels <= level) & (level <= tree.last_levels)  # the nodes present at the level
        assert shown <= set(np.nonzero(here)[0].tolist())
        assert (out / "views" / "frame_00002" / f"level_{level}.png").is_file()


def test_a_node_query_answers_with_whole_nodes(decomposed, demo_run, tmp_path):
    from n2f2.cli import main
    from n2f2.hierarchy.files import read_tree

    out, _ = decomposed
    q = tmp_path / "q"
    assert main(["query", str(demo_run), "lid of the teapot", "--mode", "node", "--decomposition", str(out),
                 "--views", "0", "--out", str(q), "--path", "--quiet"]) == 0
    answer = json.loads((q / "query.json").read_text())["nodes"]["lid of the teapot"]
    tree = read_tree(out)
    assert [p["node"] for p in answer["path"]] == tree.path(answer["nodes"][0])
    assert all(tree.levels[k] <= answer["level"] <= tree.last_levels[k] for k in answer["nodes"])


def test_decompose_refuses_a_run_without_a_field(tmp_path, demo_run, capsys):
    from n2f2.cli import main

    run = tmp_path / "run"
    shutil.copytree(demo_run, run, ignore=shutil.ignore_patterns("field.pt", "checkpoint.pt"))
    assert main(["decompose", str(run), "--quiet"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no field.pt" in err[0] and str(run) in err[0]
    assert not (run / "decomposition").exists()


def test_a_node_answer_climbs_to_the_whole_and_keeps_its_instances():
    from n2f2.query.nodes import INSTANCE_SHARE, choose_nodes

    # Tree: 0 -> (1, 2); 1 -> (3, 4); 2 -> (5, 6, 7). Levels 0, 1, 2, each node on one level.
    levels = np.array([0, 1, 1, 2, 2, 2, 2, 2])
    last = levels.copy()
    parents = np.array([-1, 0, 0, 1, 1, 2, 2, 2])
    # "table": a patch (3) matches best, its parent (1) nearly as well, the root far less.
    margin = torch.tensor([0.05, 0.95 * 0.5, 0.0, 0.5, 0.1, 0.0, 0.0, 0.0])
    a = choose_nodes(margin, levels, last, parents)
    assert (a.nodes, a.level) == ([1], 1)
    # "lid": the part (6) beats its parent (2) clearly: the part stays; its sibling 7 scores
    # within INSTANCE_SHARE of it (a second instance) and joins, 5 does not.
    margin = torch.tensor([0.0, 0.0, 0.2, 0.0, 0.0, 0.3, 0.6, INSTANCE_SHARE * 0.6 + 1e-3])
    a = choose_nodes(margin, levels, last, parents)
    assert (a.nodes, a.level) == ([6, 7], 2)
    # No node above the negatives: the best node alone.
    a = choose_nodes(torch.full((8,), -0.2), levels, last, parents)
    assert len(a.nodes) == 1


def test_an_unsplit_node_keeps_its_id_on_the_finer_level():
    from n2f2.hierarchy.build import node_ids

    # Level 0: {0,1,2,3} {4,5}; level 1: {0,1} {2,3} {4,5} (the second node unsplit);
    # level 2: {0} {1} {2,3} {4} {5}.
    kept = [np.array([0, 0, 0, 0, 1, 1]), np.array([0, 0, 1, 1, 2, 2]), np.array([0, 1, 2, 2, 3, 4])]
    nodes, parents, first, last = node_ids(kept)
    assert nodes.tolist() == [[0, 2, 4], [0, 2, 5], [0, 3, 3], [0, 3, 3], [1, 1, 6], [1, 1, 7]]
    assert parents.tolist() == [-1, -1, 0, 0, 2, 2, 1, 1]
    assert first.tolist() == [0, 0, 1, 1, 2, 2, 2, 2]
    assert last.tolist() == [0, 1, 1, 2, 2, 2, 2, 2]


def test_own_shares_by_hand():
    from n2f2.hierarchy.build import own_shares

    # On a line: 0, 1, 2 (cluster 0), then 10, 10.5 (cluster 1) and 11.2 (cluster 0). The nearest
    # neighbours are 1, 0 or 2, 1, 10.5, 10, 10.5: cluster 0 keeps 3 of its 4, cluster 1 both.
    x = np.array([0.0, 1.0, 2.0, 10.0, 10.5, 11.2])
    shares = own_shares(np.stack([x, 0 * x, 0 * x], 1), np.array([0, 0, 0, 1, 1, 0]))
    np.testing.assert_allclose(shares, [0.75, 1.0])


def test_scattered_splinters_join_the_sibling_of_nearest_feature():
    from n2f2.hierarchy.build import absorb_splinters

    # One scale, W = I, D = 2, one parent. Cluster 0 (0 degrees) fills x in [0, 1), cluster 1
    # (90 degrees) fills x in [2, 3), both compact. Cluster 2 (80 degrees, nearer to cluster 1 in
    # feature) is scattered over cluster 0's stretch, cluster 3 (10 degrees, nearer to cluster 0)
    # over cluster 1's: neither is a piece of its own, so each joins the compact sibling nearest
    # in feature, not the one it lies in.
    def rows(deg: float, n: int) -> torch.Tensor:
        r = np.deg2rad(deg)
        return torch.tensor([[np.cos(r), np.sin(r)]] * n, dtype=torch.float32)

    theta = torch.cat([rows(0, 20), rows(90, 20), rows(80, 4), rows(10, 4)])
    x = np.concatenate([np.arange(20) / 20, 2 + np.arange(20) / 20, [0.125, 0.375, 0.625, 0.875],
                        2 + np.array([0.125, 0.375, 0.625, 0.875])])
    means = np.stack([x, 0 * x, 0 * x], 1)
    labels = np.array([0] * 20 + [1] * 20 + [2] * 4 + [3] * 4)
    (out,) = absorb_splinters(theta, means, [labels], [(0, 2)], [torch.eye(2)], chunk=7)
    assert out.tolist() == [0] * 20 + [1] * 20 + [1] * 4 + [0] * 4
    # Two compact pieces stay apart whatever their size; interleaved halves become one cluster.
    (out,) = absorb_splinters(theta[:40], means[:40], [labels[:40]], [(0, 2)], [torch.eye(2)], chunk=7)
    assert out.tolist() == labels[:40].tolist()
    mixed = np.arange(40) % 2
    (out,) = absorb_splinters(theta[:40], means[:40], [mixed], [(0, 2)], [torch.eye(2)], chunk=7)
    assert len(set(out.tolist())) == 1


def test_a_node_is_read_over_the_scales_where_it_is_whole_at_its_finest():
    from n2f2.hierarchy.build import node_ids, whole_scales

    # Four candidates at field scales 0, 1, 3 and 7 of 8; the third (scale 3) is not kept as a
    # level but splits {4, 5}. Levels: {0..3} {4,5} | {0,1} {2,3} {4,5} | singletons.
    parts = [np.array([0, 0, 0, 0, 1, 1]), np.array([0, 0, 1, 1, 2, 2]), np.array([0, 0, 1, 1, 2, 3]),
             np.array([0, 1, 2, 3, 4, 5])]
    kept = [0, 1, 3]
    nodes, _, _, last = node_ids([parts[i] for i in kept])
    assert last.tolist() == [0, 1, 1, 1, 2, 2, 2, 2, 2, 2]  # node 1 = {4, 5} spans levels 0-1
    reads = whole_scales(parts, [0, 1, 3, 7], kept, nodes, last, 8)
    # Node 0 splits at the next candidate (scale 1); node 1 = {4, 5} at the unkept one (scale 3);
    # {0, 1} and {2, 3} only at the finest candidate (scale 7); the leaves run to the field's end.
    assert reads.tolist() == [[0, 1], [1, 3], [1, 7], [1, 7]] + [[7, 8]] * 6


@pytest.mark.parametrize("variant, step", [("nested", 2), ("nested", 1), ("levels", 1)])
def test_node_embeddings_equal_the_mean_unit_feature_over_gaussians_and_scales(variant, step):
    from n2f2.hierarchy.nodes import node_embeddings

    theta, means, _, _ = _known_field(per_part=6, noise=0.05)
    theta = torch.cat([theta, 0.3 * theta.flip(1)[:, :4]], 1)  # D = 12: the levels variant's 3 blocks of 4
    W = torch.randn(10, 12, generator=torch.Generator().manual_seed(3))
    dec = decompose(theta, means, W, VARIANTS[variant], step, DecomposeConfig())
    assert dec.field_scales == VARIANTS[variant].coarse_to_fine(12, step)
    emb = node_embeddings(theta, W, dec, chunk=17)
    # Reference: every Gaussian's feature at every scale of the node, formed and normalised one by one.
    for k in range(dec.num_nodes):
        members = theta[torch.from_numpy(dec.gaussian_nodes[:, dec.last_levels[k]] == k)].double()
        feats = []
        for s in range(*dec.reads[k]):
            a, b = dec.field_scales[s]
            for t in members:
                phi = W[:, a:b].double() @ t[a:b]
                feats.append(phi / phi.norm())
        torch.testing.assert_close(emb[k].double(), torch.stack(feats).mean(0), rtol=1e-4, atol=1e-5)


def test_candidate_scales_are_half_octaves_of_the_ladder():
    from n2f2.hierarchy.build import candidate_scales

    nested = VARIANTS["nested"]
    # 128 prefixes: round(2^(j/2)) for j = 0..14, repeats once; the indices are 0-based.
    dims = [i + 1 for i in candidate_scales(nested, 128, 1)]
    assert dims == [1, 2, 3, 4, 6, 8, 11, 16, 23, 32, 45, 64, 91, 128]
    assert [i + 1 for i in candidate_scales(nested, 128, 1, per_octave=1)] == [1, 2, 4, 8, 16, 32, 64, 128]
    # Step 4 of D = 48: 12 scales (d = 4 .. 48), the finest always a candidate.
    assert [nested.coarse_to_fine(48, 4)[i][1] for i in candidate_scales(nested, 48, 4)] == [4, 8, 12, 16, 24, 32, 44, 48]
    assert candidate_scales(nested, 8, 1) == list(range(8))  # at most 8 scales: all of them


def test_kmeans_pp_seeds_one_centre_in_each_far_apart_blob():
    from n2f2.hierarchy.build import kmeans_pp

    # Four blobs, 1e-3 wide, at the corners of a square of side 10, the first holding 170 of the
    # 200 points: random seeding would mostly put two or more centres in it; D^2 seeding cannot
    # (a point of a seeded blob weighs ~1e-6 against ~100 for a point of an unseeded one).
    g = torch.Generator().manual_seed(0)
    corners = torch.tensor([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0], [10.0, 10.0]])
    sizes = [170, 10, 10, 10]
    points = torch.cat([c + 1e-3 * torch.randn(n, 2, generator=g) for c, n in zip(corners, sizes)])
    blob = np.repeat(np.arange(4), sizes)
    for seed in range(5):
        picked = kmeans_pp(points, 4, torch.Generator().manual_seed(seed))
        assert sorted(blob[picked.numpy()].tolist()) == [0, 1, 2, 3], seed
