"""The stage cache of ``n2f2 run``, ``demo``, ``run-many`` and ``n2f2 bench``: a stage is
skipped when its recorded key (a hash of its inputs' content and its settings) matches the one
in ``DIR/stages.json`` and its outputs still exist. Keys hash file contents, never paths or
modification times, so a copied or touched input changes nothing and an edited one reruns."""

from __future__ import annotations

import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from ..io import commit_outputs, write_json

STAGES_FILE = "stages.json"
UNFINISHED = "unfinished"  # in a stage's record while it runs


def file_digest(path: Path, _chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(_chunk):
            h.update(block)
    return h.hexdigest()


def tree_digest(root: Path, patterns: tuple[str, ...] = ("**/*",)) -> str:
    """Content hash of every file under ``root`` matching ``patterns`` (names and bytes)."""
    h = hashlib.sha256()
    files = sorted({p for pat in patterns for p in root.glob(pat) if p.is_file()})
    for p in files:
        h.update(str(p.relative_to(root)).encode())
        h.update(file_digest(p).encode())
    return h.hexdigest()


def scene_digest(scene_dir: Path) -> str:
    """What the fitted Gaussians depend on: poses/intrinsics files and the images."""
    return tree_digest(scene_dir, ("transforms.json", "sparse/**/*", "images/*", "*.ply"))


def stage_key(**inputs) -> str:
    """A short hash of a stage's inputs (digests and settings, JSON-serialised)."""
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class StageCache:
    """The stages recorded in ``run_dir/stages.json``: ``{name: {"key", "seconds", "outputs"}}``."""

    run_dir: Path
    records: dict = field(default_factory=dict)
    ran: list = field(default_factory=list)  # stages run (not skipped) by this process
    expected: dict = field(default_factory=dict)  # {stage: seconds} estimated before the run (.estimate)

    @classmethod
    def open(cls, run_dir: Path) -> "StageCache":
        path = Path(run_dir) / STAGES_FILE
        records = json.loads(path.read_text()) if path.is_file() else {}
        return cls(Path(run_dir), records)

    def fresh(self, name: str, key: str, outputs: list[Path]) -> bool:
        """Stage ``name`` already ran with ``key`` and its outputs exist."""
        rec = self.records.get(name)
        return bool(rec and rec.get("key") == key and not rec.get(UNFINISHED) and all(p.exists() for p in outputs))

    def interrupted(self, name: str, key: str) -> bool:
        """Stage ``name`` was started with ``key`` and did not finish: what it kept (a
        checkpoint, bank records) belongs to the same inputs and may be continued."""
        rec = self.records.get(name)
        return bool(rec and rec.get("key") == key and rec.get(UNFINISHED))

    def run(self, name: str, key: str, outputs: list[Path], fn: Callable[[], object], log=print) -> bool:
        """Run ``fn`` unless stage ``name`` already ran with ``key`` and its outputs exist (what
        ``fn`` returns is dropped). The start is recorded first and kept whatever happens, so
        that a run stopped in the middle of the stage can continue it (:meth:`interrupted`,
        asked before this call). Returns True when the stage ran."""
        if self.fresh(name, key, outputs):
            log(f"[{name}] up to date (key {key}), skipped")
            return False
        log(f"[{name}] {'continuing' if self.interrupted(name, key) else 'running'}")
        self.records[name] = {"key": key, UNFINISHED: True}
        write_json(self.run_dir / STAGES_FILE, self.records, keep=True)
        start = time.perf_counter()
        fn()
        self.records[name] = {
            "key": key,
            "seconds": round(time.perf_counter() - start, 2),
            "outputs": [str(p.relative_to(self.run_dir)) for p in outputs],
        }
        write_json(self.run_dir / STAGES_FILE, self.records)
        commit_outputs()  # a finished stage stays, whatever happens to the later ones
        self.ran.append(name)
        guess = self.expected.get(name)
        beside = "" if guess is None else f" (expected ~{guess:.0f} s)" if guess >= 1 else f" (expected ~{guess:.1f} s)"
        log(f"[{name}] done in {self.records[name]['seconds']:.1f} s{beside}")
        return True
