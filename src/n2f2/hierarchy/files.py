"""The files of a decomposition folder (``n2f2 decompose RUN --out DIR``), written and read here
only:

* ``tree.json``: format ``n2f2-tree-v1``; the run, the Gaussian count, the seconds taken, the
  ``settings`` (:class:`.build.DecomposeConfig`); the levels (coarsest first: theta dims, scale label,
  quantized scale, the count of nodes present, the cut) and one record per node: ``id`` (global,
  coarsest level first), ``parent`` (null at level 0), ``level`` and ``last_level`` (the levels
  it spans unsplit: the same id in each of their columns), ``scale`` (of its last level),
  ``read_scales`` (the first and last of the field's scales its embedding is the mean over,
  :mod:`.nodes`), ``gaussians``, ``centroid``,
  ``box`` (``[[min x, y, z], [max x, y, z]]`` of its centres), ``text`` / ``relevancy`` (the
  best phrase of ``--vocabulary``, else null);
* ``gaussian_nodes.npy``: int32 ``[N, L]``, every Gaussian's node at every level;
* ``node_embeddings.npy``: float32 ``[K, E]``, each node's embedding (:mod:`.nodes`), what node
  queries score;
* ``decomposition.ply``: the run's Gaussians in the INRIA layout plus int properties ``node_0``
  (coarsest) ... ``node_{L-1}``;
* ``views/<image stem>/levels.npy`` and ``level_<l>.png`` (:mod:`.views`).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..errors import InputError
from .build import Decomposition

FORMAT = "n2f2-tree-v1"
DEFAULT_OUT = "decomposition"  # RUN/decomposition: where decompose writes and node queries look by default
TREE_NAME = "tree.json"
NODES_NAME = "gaussian_nodes.npy"
EMBEDDINGS_NAME = "node_embeddings.npy"
PLY_NAME = "decomposition.ply"
VIEWS_NAME = "views"
RESULT_NAMES = (TREE_NAME, NODES_NAME, EMBEDDINGS_NAME, PLY_NAME, VIEWS_NAME)
PLY_PREFIX = "node_"
LEVELS_NAME = "levels.npy"


def view_folder(root: str | Path, stem: str) -> Path:
    """``DIR/views/<image stem>``: a view's ``levels.npy`` and its PNGs."""
    return Path(root) / VIEWS_NAME / stem


def tree_record(
    dec: Decomposition,
    counts: np.ndarray,  # [K]
    centroids: np.ndarray,  # [K, 3]
    lo: np.ndarray,  # [K, 3]
    hi: np.ndarray,  # [K, 3]
    texts: list[Optional[str]],  # [K]
    relevancies: np.ndarray,  # [K]
    meta: dict[str, Any],
) -> dict:
    """``tree.json``'s content."""
    levels = [
        {
            "level": level,
            "dims": list(dec.level_scales[level]),
            "scale_label": dec.level_labels[level],
            "scale": dec.level_values[level],
            "nodes": int(len(dec.nodes_at(level))),
            "cut": dec.thresholds[level],
        }
        for level in range(dec.num_levels)
    ]
    nodes = [
        {
            "id": k,
            "parent": None if dec.parents[k] < 0 else int(dec.parents[k]),
            "level": int(dec.levels[k]),
            "last_level": int(dec.last_levels[k]),
            "scale": dec.level_values[int(dec.last_levels[k])],
            "read_scales": [dec.field_labels[int(dec.reads[k, 0])], dec.field_labels[int(dec.reads[k, 1]) - 1]],
            "gaussians": int(counts[k]),
            "centroid": [float(x) for x in centroids[k]],
            "box": [[float(x) for x in lo[k]], [float(x) for x in hi[k]]],
            "text": texts[k],
            "relevancy": None if np.isnan(relevancies[k]) else float(relevancies[k]),
        }
        for k in range(dec.num_nodes)
    ]
    return {
        "format": FORMAT,
        **meta,
        "num_levels": dec.num_levels,
        "levels": levels,
        "candidates": dec.candidates,
        "nodes": nodes,
    }


@dataclass
class LoadedTree:
    """A decomposition folder read back: what node queries and the viewer need."""

    root: Path
    tree: dict
    gaussian_nodes: np.ndarray  # [N, L] int64
    embeddings: np.ndarray  # [K, E] float32

    @property
    def num_levels(self) -> int:
        return int(self.gaussian_nodes.shape[1])

    @cached_property
    def levels(self) -> np.ndarray:  # [K] first (coarsest) level of each node
        return np.array([n["level"] for n in self.tree["nodes"]], dtype=np.int64)

    @cached_property
    def last_levels(self) -> np.ndarray:  # [K] last (finest) level each node spans
        return np.array([n.get("last_level", n["level"]) for n in self.tree["nodes"]], dtype=np.int64)

    @cached_property
    def parents(self) -> np.ndarray:  # [K] parent id, -1 at level 0
        return np.array([-1 if n["parent"] is None else n["parent"] for n in self.tree["nodes"]], dtype=np.int64)

    def path(self, node: int) -> list[int]:
        """``node`` and its ancestors, the node first."""
        parents = self.parents
        out = [int(node)]
        while parents[out[-1]] >= 0:
            out.append(int(parents[out[-1]]))
        return out


def read_tree(root: str | Path, num_gaussians: Optional[int] = None) -> LoadedTree:
    """Read a decomposition folder; one :class:`InputError` naming the file for a missing or
    inconsistent one (``num_gaussians``: the run's count, checked)."""
    root = Path(root)
    path = root / TREE_NAME
    if not path.is_file():
        raise InputError(root, "no tree.json: not a decomposition (run `n2f2 decompose RUN` first)")
    try:
        tree = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(path, f"cannot read the tree ({e})") from None
    if not isinstance(tree, dict) or tree.get("format") != FORMAT:
        raise InputError(path, f"not a {FORMAT} tree")
    arrays = {}
    for name in (NODES_NAME, EMBEDDINGS_NAME):
        try:
            arrays[name] = np.load(root / name, allow_pickle=False)
        except (OSError, ValueError) as e:
            raise InputError(root / name, f"cannot read ({type(e).__name__}: {e})") from None
    nodes, emb = arrays[NODES_NAME], arrays[EMBEDDINGS_NAME]
    K = len(tree.get("nodes", []))
    if (
        nodes.ndim != 2
        or nodes.shape[1] != tree.get("num_levels")
        or (nodes.size and not 0 <= nodes.min() <= nodes.max() < K)
    ):
        raise InputError(root / NODES_NAME, f"does not match tree.json ({tree.get('num_levels')} levels, {K} nodes)")
    if num_gaussians is not None and nodes.shape[0] != num_gaussians:
        raise InputError(
            root / NODES_NAME, f"holds {nodes.shape[0]} Gaussians but the run has {num_gaussians}: decompose it again"
        )
    if emb.ndim != 2 or emb.shape[0] != K:
        raise InputError(root / EMBEDDINGS_NAME, f"needs one row per node ({K}), has shape {list(emb.shape)}")
    return LoadedTree(root, tree, nodes.astype(np.int64), emb.astype(np.float32))


def read_ply_nodes(path: str | Path) -> np.ndarray:  # -> [N, L] int64
    """The ``node_<l>`` properties of a ``decomposition.ply``, coarsest first."""
    from ..gaussians.ply import read_ply_ints

    found = read_ply_ints(path, PLY_PREFIX)
    names = [f"{PLY_PREFIX}{level}" for level in range(len(found))]
    if sorted(found) != sorted(names):
        raise InputError(Path(path), f"node properties are not node_0 .. node_{len(found) - 1}: {sorted(found)}")
    return np.stack([found[n] for n in names], axis=1) if names else np.zeros((0, 0), np.int64)
