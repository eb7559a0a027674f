"""``--executor ray``: ``n2f2 segments`` and ``n2f2 run-many`` as Ray tasks give exactly what the
serial path gives, survive a killed worker, resume with only the missing images, report a bad
input once while the other tasks finish, and take a task still running when the driver stops
down with its worker. One local Ray instance (2 CPUs) serves the module."""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from n2f2.cli import build_parser, main
from n2f2.segments.setup import SegmentsSetup

VIEWS, WIDTH, HEIGHT = 6, 80, 60
RUN_OPTS = ["--fit-steps", "20", "--train-steps", "8", "--dim", "16", "--quiet"]


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def ray_instance():
    ray = pytest.importorskip("ray")
    cloudpickle = pytest.importorskip("ray.cloudpickle")

    # The hooks below (a source that kills its worker, one that counts its calls) are defined in
    # this test module, which Ray workers cannot import: ship them by value.
    cloudpickle.register_pickle_by_value(sys.modules[__name__])
    ray.init(address="local", num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1",
             log_to_driver=False)
    yield ray
    ray.shutdown()


@pytest.fixture(scope="module")
def scenes(tmp_path_factory, tiny_random_clip):
    """Two small generated demo scenes (different seeds) and a tiny random CLIP saved as a folder."""
    from n2f2.data.synthetic import generate_demo_scene

    root = tmp_path_factory.mktemp("distributed")
    out = {}
    for name, seed in (("alpha", 0), ("beta", 1)):
        generate_demo_scene(root / name, num_views=VIEWS, width=WIDTH, height=HEIGHT, seed=seed,
                            labelled_views=[1, 4], show_progress=False)
        out[name] = root / name
    model, tokenizer = tiny_random_clip
    model.save_pretrained(root / "clip")
    tokenizer.save_pretrained(root / "clip")
    out["clip"] = root / "clip"
    out["root"] = root
    return out


def _segments_args(scene: Path, out: Path, teacher: str, clip: Path) -> list[str]:
    if teacher == "classical":
        teacher_args = ["--segmenter", "classical", "--encoder", "clip", "--model", str(clip)]
    else:
        teacher_args = ["--segmenter", "ground-truth", "--encoder", "captions"]
    return ["segments", str(scene), *teacher_args, "--depth-source", "gt", "--out", str(out), "--quiet"]


@pytest.fixture(scope="module")
def serial_banks(scenes):
    """The serial banks of scene alpha (the reference), per teacher."""
    banks = {}
    for teacher in ("classical", "ground-truth"):
        out = scenes["root"] / f"serial-bank-{teacher}"
        assert main(_segments_args(scenes["alpha"], out, teacher, scenes["clip"])) == 0
        banks[teacher] = out
    return banks


def assert_same_bank(a: Path, b: Path) -> None:
    """Every record file equal (arrays bit for bit), and the same fitted quantile transform."""
    meta_a, meta_b = (json.loads((p / "bank.json").read_text()) for p in (a, b))
    assert meta_a["complete"] and meta_b["complete"]
    assert meta_a["scene"] == meta_b["scene"]
    assert meta_a["quantile"] == meta_b["quantile"] and meta_a["counts"] == meta_b["counts"]
    for image in meta_a["scene"]["images"]:
        ra, rb = a / image["name"], b / image["name"]
        names = sorted(p.name for p in ra.iterdir())
        assert names == sorted(p.name for p in rb.iterdir())
        for name in names:
            if name.endswith(".npy"):
                x, y = np.load(ra / name), np.load(rb / name)
                assert x.dtype == y.dtype and x.shape == y.shape, (image["name"], name)
                assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), (image["name"], name)
            else:
                assert (ra / name).read_bytes() == (rb / name).read_bytes(), (image["name"], name)


# ----------------------------------------------------------------------------- test hooks
class _Source:
    """Wraps a segment source; ``hook(index)`` runs in the worker before each image."""

    def __init__(self, inner, hook):
        self.inner, self.hook = inner, hook
        self.segmenter_spec, self.encoder_spec = inner.segmenter_spec, inner.encoder_spec

    def prepare(self, stems):
        self.inner.prepare(stems)

    def extract(self, index, stem, image):
        self.hook(index)
        return self.inner.extract(index, stem, image)


@dataclass(frozen=True)
class KillOnce:
    """The first attempt at image ``victim`` kills its own worker process (SIGKILL), once."""

    setup: SegmentsSetup
    marker: str
    victim: int

    def build(self):
        scene, source, depth = self.setup.build()

        def hook(index):
            if index == self.victim and not os.path.exists(self.marker):
                Path(self.marker).write_text(str(os.getpid()))
                os.kill(os.getpid(), 9)

        return scene, _Source(source, hook), depth


@dataclass(frozen=True)
class CountCalls:
    """Leaves one file per extracted image in ``calls``; image ``crash_at`` raises (a crash)."""

    setup: SegmentsSetup
    calls: str
    crash_at: int = -1

    def build(self):
        scene, source, depth = self.setup.build()

        def hook(index):
            if index == self.crash_at:
                raise RuntimeError(f"crash at image {index}")
            (Path(self.calls) / f"{index}-{os.getpid()}-{os.urandom(4).hex()}").touch()

        return scene, _Source(source, hook), depth


def _job(scene: Path, teacher: str, clip: Path):
    """The bank job `n2f2 segments` makes of the test's flags (its lift settings are the preset's)."""
    from n2f2.segments.commands import job_from_args

    args = build_parser().parse_args(_segments_args(scene, Path("unused"), teacher, clip))
    return job_from_args(args, segmenter=args.segmenter, encoder=args.encoder, sam_model=args.sam_model)


def _setup(scene: Path, teacher: str, clip: Path) -> SegmentsSetup:
    from n2f2.segments.stage import setup_of

    return setup_of(_job(scene, teacher, clip))


def _build_with(setup, out: Path, lift) -> dict:
    from n2f2.distributed import RayExecutor
    from n2f2.segments.bank import build_bank

    scene, source, depth = setup.setup.build()
    with RayExecutor() as executor:
        return build_bank(scene, source, depth, out, depth_source="gt", lift=lift, progress=False,
                          executor=executor, worker_setup=setup)


# ----------------------------------------------------------------------------- segments
@pytest.mark.parametrize("teacher", ["classical", "ground-truth"])
def test_ray_bank_equals_serial_bank(ray_instance, scenes, serial_banks, teacher, tmp_path):
    out = tmp_path / "bank"
    assert main(_segments_args(scenes["alpha"], out, teacher, scenes["clip"]) + ["--executor", "ray"]) == 0
    assert_same_bank(serial_banks[teacher], out)


def test_a_killed_worker_is_retried_and_the_bank_is_the_same(ray_instance, scenes, serial_banks, tmp_path):
    marker = tmp_path / "killed"
    setup = KillOnce(_setup(scenes["alpha"], "ground-truth", scenes["clip"]), str(marker), victim=2)
    _build_with(setup, tmp_path / "bank", _job(scenes["alpha"], "ground-truth", scenes["clip"]).lift)
    assert marker.is_file()  # a worker really died on image 2
    assert int(marker.read_text()) != os.getpid()  # ... and it was not this process
    assert_same_bank(serial_banks["ground-truth"], tmp_path / "bank")


def test_an_interrupted_run_redoes_only_the_missing_images(ray_instance, scenes, serial_banks, tmp_path):
    base = _setup(scenes["alpha"], "ground-truth", scenes["clip"])
    lift = _job(scenes["alpha"], "ground-truth", scenes["clip"]).lift
    out, calls = tmp_path / "bank", tmp_path / "calls"
    (calls / "first").mkdir(parents=True)
    with pytest.raises(RuntimeError, match="crash at image 3"):
        _build_with(CountCalls(base, str(calls / "first"), crash_at=3), out, lift)
    stems = [f"frame_{i + 1:05d}" for i in range(VIEWS)]
    kept = {i for i, s in enumerate(stems) if (out / s).is_dir()}
    assert 3 not in kept and not json.loads((out / "bank.json").read_text())["complete"]

    (calls / "again").mkdir()
    report = _build_with(CountCalls(base, str(calls / "again")), out, lift)
    computed = [int(p.name.split("-")[0]) for p in (calls / "again").iterdir()]
    assert sorted(computed) == sorted(set(range(VIEWS)) - kept)  # each missing image once, no other
    assert report["timing"]["images_extracted_now"] == VIEWS - len(kept)
    assert_same_bank(serial_banks["ground-truth"], out)


@dataclass(frozen=True)
class SlowBesideACrash:
    """Item 0 writes its worker's pid to ``marker`` and works for ten minutes; item 1 raises (a
    bug) once item 0 is running."""

    marker: str

    def __call__(self, item: int) -> int:
        if item == 0:
            Path(self.marker + ".part").write_text(str(os.getpid()))
            os.replace(self.marker + ".part", self.marker)
            for _ in range(6000):
                time.sleep(0.1)
            return item
        while not os.path.exists(self.marker):
            time.sleep(0.05)
        raise RuntimeError("a bug in one task")


def _running(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (FileNotFoundError, ProcessLookupError):
        return False
    return state not in ("Z", "X")  # a zombie has exited


@pytest.mark.skipif(not Path("/proc/self/stat").exists(), reason="reads process states from /proc")
def test_a_task_still_running_when_the_caller_stops_goes_with_its_worker(ray_instance, tmp_path):
    # An interrupt (Ray's default cancel) can land inside an import and leave the worker's modules
    # half initialised for every later task there: the running task's worker must be killed.
    from n2f2.distributed import RayExecutor

    marker = str(tmp_path / "slow-worker-pid")
    with pytest.raises(RuntimeError, match="a bug in one task"):
        for _ in RayExecutor().map(SlowBesideACrash(marker), [0, 1]):
            pass
    pid = int(Path(marker).read_text())
    assert pid != os.getpid()
    deadline = time.monotonic() + 60
    while _running(pid) and time.monotonic() < deadline:
        time.sleep(0.1)
    assert not _running(pid)


def test_a_bad_image_is_reported_once_and_the_others_finish(ray_instance, scenes, tmp_path, capsys):
    scene = tmp_path / "scene"
    shutil.copytree(scenes["alpha"], scene)
    (scene / "regions" / "frame_00004.npy").write_bytes(b"not an array")
    out = tmp_path / "bank"
    rc = main(_segments_args(scene, out, "ground-truth", scenes["clip"]) + ["--executor", "ray"])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("cannot read ground-truth regions") == 1 and "frame_00004.npy" in err
    last = err.strip().splitlines()[-1]
    assert last.startswith("n2f2 segments: error:") and "1 of 6 images failed (frame_00004.png)" in last
    done = sorted(p.name for p in out.iterdir() if p.is_dir())
    assert done == [f"frame_{i:05d}" for i in (1, 2, 3, 5, 6)]


def test_without_ray_one_line_and_the_serial_path_never_imports_it(scenes, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # `import ray` now fails, as when it is not installed
    args = _segments_args(scenes["alpha"], tmp_path / "bank", "ground-truth", scenes["clip"])
    assert main(args + ["--executor", "ray"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.splitlines() == [err] and err.endswith("install the extra: pip install 'n2f2[ray]'")
    assert main(args) == 0  # serial: would raise ImportError if it imported Ray


def test_ray_options_are_checked_before_any_work(ray_instance, scenes, tmp_path, capsys):
    import socket

    from n2f2.distributed import RayExecutor, check_ray_address
    from n2f2.errors import InputError

    args = _segments_args(scenes["alpha"], tmp_path / "bank", "ground-truth", scenes["clip"])
    assert main(args + ["--ray-address", "auto"]) == 2
    assert capsys.readouterr().err.strip().endswith("--ray-address needs --executor ray")
    with pytest.raises(InputError, match="HOST:PORT"):
        check_ray_address("head-without-port")
    with socket.socket() as s:  # a port nobody listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(InputError, match=f"no Ray head node answers at 127.0.0.1:{port}"):
        check_ray_address(f"127.0.0.1:{port}", timeout=2)
    with pytest.raises(InputError, match="no node of the Ray cluster has 3 CPU"):  # the instance has 2
        list(RayExecutor(cpus_per_task=3).map(str, [1]))
    assert not (tmp_path / "bank").exists()


# ----------------------------------------------------------------------------- run-many
@pytest.fixture(scope="module")
def serial_runs(scenes):
    runs = {}
    for name in ("alpha", "beta"):
        runs[name] = scenes["root"] / "serial-runs" / name
        assert main(["run", str(scenes[name]), "--out", str(runs[name]), *RUN_OPTS]) == 0
    return runs


@pytest.fixture(scope="module")
def ray_many(ray_instance, scenes):
    out = scenes["root"] / "many"
    assert main(["run-many", str(scenes["alpha"]), str(scenes["beta"]), "--out", str(out),
                 "--executor", "ray", *RUN_OPTS]) == 0
    return out


def test_run_many_on_ray_matches_serial_runs(serial_runs, ray_many):
    import torch

    from n2f2.io import load_torch

    summary = json.loads((ray_many / "summary.json").read_text())
    assert [r["scene"] for r in summary["scenes"]] == ["alpha", "beta"]
    for row in summary["scenes"]:
        name = row["scene"]
        serial, ray_run = serial_runs[name], ray_many / name
        assert row["status"] == "ok" and set(row["stages"]) == {"fit-gaussians", "segments", "train", "eval"}
        assert all(st["ran"] for st in row["stages"].values())
        assert_same_bank(serial / "bank", ray_run / "bank")
        a, b = (load_torch(r / "field.pt") for r in (serial, ray_run))
        flat_a, flat_b = _tensors(a), _tensors(b)
        assert flat_a.keys() == flat_b.keys() and flat_a
        for key in flat_a:
            assert torch.equal(flat_a[key], flat_b[key]), key
        ev_a, ev_b = (json.loads((r / "eval" / "eval.json").read_text())["scores"] for r in (serial, ray_run))
        for mode in ("composite", "explicit", "oracle"):
            for box in ("exact", "scaled"):
                assert ev_a[mode][box]["miou"] == ev_b[mode][box]["miou"]
                assert row["miou"][mode][box] == ev_a[mode][box]["miou"]  # the summary's numbers
    md = (ray_many / "summary.md").read_text()
    assert "| alpha | ok |" in md and "| beta | ok |" in md


def _tensors(obj, prefix="") -> dict:
    import torch

    if isinstance(obj, torch.Tensor):
        return {prefix: obj}
    if isinstance(obj, dict):
        return {k: v for key, val in obj.items() for k, v in _tensors(val, f"{prefix}/{key}").items()}
    if isinstance(obj, (list, tuple)):
        return {k: v for i, val in enumerate(obj) for k, v in _tensors(val, f"{prefix}/{i}").items()}
    return {}


@pytest.mark.parametrize("executor", ["serial", "ray"])
def test_run_many_reports_a_broken_scene_once_and_finishes_the_other(ray_many, scenes, executor, tmp_path,
                                                                     capsys):
    out = tmp_path / "many"
    shutil.copytree(ray_many / "alpha", out / "alpha")  # alpha's stages are cached
    broken = tmp_path / "broken"
    shutil.copytree(scenes["beta"], broken)
    (broken / "transforms.json").write_text("{ not json")
    rc = main(["run-many", str(scenes["alpha"]), str(broken), "--out", str(out), "--executor", executor, *RUN_OPTS])
    err = capsys.readouterr().err
    assert rc == 2
    failure_lines = [line for line in err.splitlines() if "transforms.json" in line]
    assert len(failure_lines) == 1 and failure_lines[0].startswith("run-many: broken failed:")
    last = err.strip().splitlines()[-1]
    assert last.startswith("n2f2 run-many: error: 1 of 2 scenes failed: broken")
    summary = json.loads((out / "summary.json").read_text())
    alpha, bad = summary["scenes"]
    assert (alpha["scene"], alpha["status"], bad["scene"], bad["status"]) == ("alpha", "ok", "broken", "failed")
    assert not any(st["ran"] for st in alpha["stages"].values())  # the content-keyed cache held
    assert summary["executor"] == executor
    assert alpha["miou"] == json.loads((ray_many / "summary.json").read_text())["scenes"][0]["miou"]
    assert "| broken | failed |" in (out / "summary.md").read_text()
