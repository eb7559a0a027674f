"""``n2f2 demo`` and ``n2f2 run``: the stages in data-flow order, each cached on its inputs.

A stage is skipped when its recorded key (a hash of its inputs' content and its settings)
matches the one in ``RUN/stages.json`` and its outputs still exist.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from .errors import InputError
from .io import write_json

STAGES_FILE = "stages.json"


# ----------------------------------------------------------------------------- caching
def file_digest(path: Path, _chunk: int = 1 << 20) -> str:
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


def stage_key(**inputs) -> str:
    return hashlib.sha256(json.dumps(inputs, sort_keys=True, default=str).encode()).hexdigest()[:16]


@dataclass
class StageCache:
    run_dir: Path
    records: dict = field(default_factory=dict)

    @classmethod
    def open(cls, run_dir: Path) -> "StageCache":
        path = run_dir / STAGES_FILE
        records = json.loads(path.read_text()) if path.is_file() else {}
        return cls(run_dir, records)

    def run(self, name: str, key: str, outputs: list[Path], fn: Callable[[], None], log=print) -> bool:
        """Run ``fn`` unless stage ``name`` already ran with ``key`` and its outputs exist.
        Returns True when the stage ran."""
        rec = self.records.get(name)
        if rec and rec.get("key") == key and all(p.exists() for p in outputs):
            log(f"[{name}] up to date (key {key}), skipped")
            return False
        log(f"[{name}] running")
        start = time.perf_counter()
        fn()
        self.records[name] = {"key": key, "seconds": round(time.perf_counter() - start, 2),
                              "outputs": [str(p.relative_to(self.run_dir)) for p in outputs]}
        write_json(self.run_dir / STAGES_FILE, self.records)
        log(f"[{name}] done in {self.records[name]['seconds']:.1f} s")
        return True


# ----------------------------------------------------------------------------- commands
def _cmd_demo(args: argparse.Namespace) -> int:
    from .data.synthetic import generate_demo_scene, write_contact_sheet

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    scene_dir = out / "scene"
    start = time.perf_counter()
    key = stage_key(views=args.views, width=args.width, height=args.height, seed=args.seed)
    cache = StageCache.open(out)
    cache.run("demo-scene", key, [scene_dir / "transforms.json", scene_dir / "regions.json"],
              lambda: generate_demo_scene(scene_dir, num_views=args.views, width=args.width,
                                          height=args.height, seed=args.seed))
    sheet = out / "contact_sheet.png"
    write_contact_sheet(scene_dir, sheet)
    print(f"demo scene: {scene_dir}")
    print(f"contact sheet: {sheet}")
    print(f"total {time.perf_counter() - start:.1f} s")
    return 0


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "demo", help="generate the built-in demo scene and run the pipeline on it",
        description="Generate the built-in synthetic tabletop scene (exact ground truth at part, "
                    "object and group level) and write a contact sheet of views and masks.")
    p.add_argument("--out", default="demo_out", help="output folder (default: demo_out)")
    p.add_argument("--views", type=int, default=40, help="number of views (default: 40)")
    p.add_argument("--width", type=int, default=160, help="image width (default: 160)")
    p.add_argument("--height", type=int, default=120, help="image height (default: 120)")
    p.add_argument("--seed", type=int, default=0, help="random seed (default: 0)")
    p.set_defaults(func=_cmd_demo)
