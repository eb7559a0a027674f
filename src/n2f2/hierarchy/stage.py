"""The hierarchy stage's runner: ``n2f2 decompose`` builds a run's hierarchy through
:func:`run_decompose`, which checks the run and the vocabulary and claims the output folder
before any work, reads the field at the Gaussian centres, decomposes (:mod:`.build`), labels the
nodes, writes the folder's files (:mod:`.files`) and the requested views (:mod:`.views`), and
prints the summary line."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional, Sequence

import numpy as np

from ..errors import InputError
from .build import DecomposeConfig
from .files import DEFAULT_OUT

Log = Callable[[str], None]
ALL_VIEWS = "all"


@dataclass
class DecomposeJob:
    """One decomposition: what ``n2f2 decompose`` takes on its command line."""

    run_dir: Path  # trained run folder (field.pt + gaussians.ply)
    out: Optional[Path] = None  # None: RUN/decomposition
    vocabulary: Optional[Path] = None  # one phrase a line: each node's best-matching text
    views: Sequence[str] = ()  # image stems to write levels.npy for; ("all",): every view
    scene: Optional[Path] = None  # None: the run's
    config: DecomposeConfig = field(default_factory=DecomposeConfig)
    device: str = "cpu"
    force: bool = False
    progress: bool = True


def read_vocabulary(path: Path) -> list[str]:
    """The phrases of a vocabulary file: one a line, blank lines and ``#`` comments skipped."""
    try:
        lines = Path(path).read_text(encoding="utf-8").splitlines()
    except (OSError, UnicodeDecodeError) as e:
        raise InputError(path, f"cannot read the vocabulary ({type(e).__name__}: {e})") from None
    phrases = list(dict.fromkeys(s.strip() for s in lines if s.strip() and not s.strip().startswith("#")))
    if not phrases:
        raise InputError(path, "the vocabulary holds no phrase (one phrase a line)")
    return phrases


def _check_run(run_dir: Path) -> None:
    if not run_dir.is_dir():
        raise InputError(run_dir, "run directory does not exist")
    if not (run_dir / "field.pt").is_file():
        raise InputError(run_dir, "no field.pt in the run directory: not a trained run (run `n2f2 train` first)")
    if not (run_dir / "gaussians.ply").is_file():
        raise InputError(run_dir, "no gaussians.ply in the run directory")


def _view_indices(scene, stems: Sequence[str]) -> list[int]:
    if list(stems) == [ALL_VIEWS]:
        return list(range(len(scene.cameras)))
    names = {Path(n).stem: i for i, n in enumerate(scene.image_names)}
    missing = [s for s in stems if s not in names]
    if missing:
        raise InputError(scene.root, f"no view named {', '.join(missing)} (image stems, or --views all)")
    return [names[s] for s in stems]


def run_decompose(job: DecomposeJob, log: Log = print) -> dict:
    """Decompose ``job.run_dir`` into ``job.out``; returns the tree record."""
    import torch

    from ..field import gaussian_features, load_field
    from ..field.relevancy import DEFAULT_NEGATIVES
    from ..field.variants import get_variant
    from ..gaussians import read_ply
    from ..io import claim_out_dir, remove_results
    from ..train.runs import load_run_scene
    from .build import decompose
    from .files import RESULT_NAMES

    run_dir = Path(job.run_dir)
    _check_run(run_dir)
    phrases = read_vocabulary(job.vocabulary) if job.vocabulary else []
    out = Path(job.out) if job.out else run_dir / DEFAULT_OUT
    present = claim_out_dir(out, RESULT_NAMES, force=job.force, resume_flag=None)
    fld, meta = load_field(run_dir / "field.pt", job.device)
    fld.requires_grad_(False)
    gaussians = read_ply(run_dir / "gaussians.ply", device=job.device)
    scene = load_run_scene(run_dir, meta, job.scene) if job.views else None
    if job.views and scene is None:
        raise InputError(run_dir, "the run records no scene folder that exists: pass --scene DATA for --views")
    views = _view_indices(scene, job.views) if job.views else []
    encoder = None
    if phrases:  # the text encoder is found (or refused) before anything is replaced
        from ..segments.encoders import get_encoder

        if not meta.get("encoder_spec"):
            raise InputError(run_dir / "field.pt", "field metadata names no text encoder: --vocabulary cannot be used")
        encoder = get_encoder(meta["encoder_spec"], job.device)
    remove_results(out, present)
    t0 = time.perf_counter()
    with torch.no_grad():
        theta = gaussian_features(fld, gaussians.means).float().cpu()
    cfg = meta.get("config", {})
    dec = decompose(
        theta,
        gaussians.means,
        fld.W,
        get_variant(str(cfg.get("variant", "nested"))),
        int(cfg.get("step_size", 1)),
        job.config,
    )
    seconds = time.perf_counter() - t0
    settings = dataclasses.asdict(job.config)
    record = _write(out, run_dir, dec, theta, fld.W, gaussians, phrases, encoder, DEFAULT_NEGATIVES, seconds, settings)
    if views:
        _write_views(out, scene, views, gaussians, dec.gaussian_nodes, job.progress)
    counts = ", ".join(str(lv["nodes"]) for lv in record["levels"])
    log(
        f"decompose: {dec.num_levels} levels ({counts} nodes) of {theta.shape[0]} Gaussians in {seconds:.1f} s"
        + (f", {len(views)} views" if views else "")
        + f" -> {out}"
    )
    return record


def _write(
    out: Path, run_dir: Path, dec, theta, W, gaussians, phrases, encoder, negatives, seconds: float, settings: dict
) -> dict:
    """tree.json, gaussian_nodes.npy, node_embeddings.npy and decomposition.ply."""
    import torch

    from ..gaussians.ply import write_ply
    from ..io import write_json, write_npy
    from .files import EMBEDDINGS_NAME, NODES_NAME, PLY_NAME, PLY_PREFIX, TREE_NAME, tree_record
    from .nodes import best_phrases, node_embeddings, node_geometry

    emb = node_embeddings(theta, W, dec)
    counts, centroids, lo, hi = node_geometry(gaussians.means.detach().cpu().numpy().astype(np.float64), dec)
    if phrases:
        texts = torch.as_tensor(encoder.encode_text(phrases)).float().cpu()
        negs = torch.as_tensor(encoder.encode_text(list(negatives))).float().cpu()
        labels, rel = best_phrases(emb, phrases, texts, negs)
    else:
        labels, rel = best_phrases(emb, [], torch.zeros(0), torch.zeros(0))
    meta = {
        "run": str(run_dir.resolve()),
        "num_gaussians": int(dec.gaussian_nodes.shape[0]),
        "seconds": seconds,
        "settings": settings,
    }
    record = tree_record(dec, counts, centroids, lo, hi, labels, rel, meta)
    write_json(out / TREE_NAME, record)
    write_npy(out / NODES_NAME, dec.gaussian_nodes)
    write_npy(out / EMBEDDINGS_NAME, emb.numpy().astype(np.float32))
    extra = {f"{PLY_PREFIX}{level}": dec.gaussian_nodes[:, level] for level in range(dec.num_levels)}
    write_ply(out / PLY_NAME, gaussians, extra)
    return record


def _write_views(out: Path, scene, views: list[int], gaussians, gaussian_nodes: np.ndarray, progress: bool) -> None:
    """views/<stem>/levels.npy and one PNG per level."""
    from tqdm import tqdm

    from ..io import make_dirs, write_npy, write_png
    from .files import LEVELS_NAME, view_folder
    from .views import node_id_maps, palette

    for i in tqdm(views, desc="views", unit="view", disable=not progress, leave=False):
        folder = view_folder(out, Path(scene.image_names[i]).stem)
        make_dirs(folder)
        maps = node_id_maps(gaussians, gaussian_nodes, scene.cameras[i])
        write_npy(folder / LEVELS_NAME, maps)
        for level, ids in enumerate(maps):
            write_png(folder / f"level_{level}.png", palette(ids))
