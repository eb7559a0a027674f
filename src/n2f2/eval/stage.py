"""The evaluation stage's runner: ``n2f2 eval`` and ``n2f2 run`` / ``demo`` / ``run-many`` score a
run on labels through :func:`run_eval`, which chooses the protocol (:mod:`.protocols`), claims
the output folder, checks every input before anything is replaced, evaluates, writes the report
and prints its summary. The bench scores its variants (and the training-free lift, through
``EvalJob.engine``) with it too."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path
from typing import Any, Callable

from ..errors import InputError
from .job import EvalJob

Log = Callable[[str], None]
__all__ = ["EvalJob", "run_eval"]


def run_eval(job: EvalJob, log: Log = print) -> Any:
    """Score ``job.run_dir`` on ``job.labels`` into ``job.out`` and return the protocol's result
    (:class:`~n2f2.eval.runner.EvalResult` for the 2D protocol)."""
    from ..io import claim_out_dir, remove_results
    from ..query.engine import QueryConfig, QueryEngine
    from .protocols import choose_protocol
    from .reports import eval_results
    from .runner import load_eval

    protocol = choose_protocol(job.protocol, Path(job.labels))
    protocol.check(job)
    if job.query_config is None:
        job = replace(job, query_config=QueryConfig())  # the caller's job stays as it was
    out = Path(job.out) if job.out else Path(job.run_dir) / "eval"
    present = claim_out_dir(out, eval_results(out), force=job.force, resume_flag=None)
    if job.compare is not None:
        if "eval.json" in present and Path(job.compare).resolve() == (out / "eval.json").resolve():
            raise InputError(
                job.compare, "--compare names the eval.json this evaluation replaces: copy it elsewhere first"
            )
        load_eval(job.compare)  # fail on a bad comparison file before any work
    engine = job.engine  # one engine (and text encoder) for every protocol and the budget
    if engine is None and (job.budget or protocol.engine):
        engine = QueryEngine.from_run(
            job.run_dir, device=job.device, scene=job.scene, config=job.query_config, encoder=job.encoder
        )
    if protocol.selects_in_3d:
        from .protocol3d import modes_3d

        modes_3d(engine, job.modes)  # before any work: the 3D protocol has no oracle mode
    if job.budget:
        assert engine is not None  # opened above for the budget
        bank = job.bank or engine.meta.get("bank")
        if not bank or not Path(bank).is_dir():  # before any work: the teacher is the segment bank
            raise InputError(
                Path(bank) if bank else Path(job.run_dir),
                "--budget needs the run's segment bank (the teacher): pass --bank DIR",
            )
    return protocol.evaluate(job, engine, out, lambda: remove_results(out, present), log)
