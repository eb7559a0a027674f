"""The evaluation protocols ``n2f2 eval --protocol`` chooses from, as registered objects (after
:mod:`n2f2.field.variants`): each knows the options it reads, whether it scores through a
query engine opened once for the run, and how it evaluates, writes its report and summarises
it. :func:`n2f2.eval.stage.run_eval` asks the protocol, never its name."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Optional

from ..errors import InputError
from .job import EvalJob

Log = Callable[[str], None]
# (job, engine or None, output folder, called once the inputs are checked, log) -> result
Evaluate = Callable[[EvalJob, Any, Path, Callable[[], None], Log], Any]

# Options of `n2f2 eval` that only some protocols read: flag -> whether a job sets it.
OPTIONAL_INPUTS: dict[str, Callable[[EvalJob], bool]] = {
    "--compare": lambda j: j.compare is not None,
    "--budget": lambda j: j.budget,
    "--query-types": lambda j: j.query_types is not None,
    "--bank": lambda j: j.bank is not None,
    "--skip-missing-frames": lambda j: j.skip_missing_frames,
    "--rescale-labels": lambda j: j.rescale_labels,
}


@dataclass(frozen=True)
class EvalProtocol:
    """One way of scoring a run on labels."""

    name: str
    description: str  # for --help
    reads: tuple[str, ...]  # the OPTIONAL_INPUTS flags it reads; the others are refused
    engine: bool  # scores through one QueryEngine of the run (else the 2D runner opens the field)
    selects_in_3d: bool  # scores Gaussians selected in 3D (modes without a 3D selection are refused)
    evaluate: Evaluate

    def check(self, job: EvalJob) -> None:
        """Refuse options this protocol would ignore."""
        refused = [flag for flag, given in OPTIONAL_INPUTS.items() if flag not in self.reads and given(job)]
        if refused:
            raise InputError(None, f"{', '.join(refused)} do(es) not apply to --protocol {self.name}")


def _eval_config(job: EvalJob):
    from .runner import EvalConfig

    return EvalConfig(
        modes=tuple(job.modes) if job.modes else None,
        missing_frames="skip" if job.skip_missing_frames else "error",
        rescale_labels=job.rescale_labels,
        progress=job.progress,
    )


def _protocol3d_config(job: EvalJob):
    from .protocol3d import Protocol3dConfig

    c = _eval_config(job)
    return Protocol3dConfig(missing_frames=c.missing_frames, rescale_labels=c.rescale_labels, progress=c.progress)


def _labels_2d(job: EvalJob, engine, out: Path, on_ready: Callable[[], None], log: Log, with_3d: bool = False):
    """LangSplat's LERF-OVS protocol on rendered relevancy maps; ``with_3d`` the 3D protocol
    beside it, with ``job.budget`` the loss budget."""
    from .reports import mode_summary_lines, protocol3d_summary_lines, write_eval_outputs
    from .runner import evaluate_run

    config = _eval_config(job)
    result = evaluate_run(
        job.run_dir,
        job.labels,
        scene=job.scene,
        bank=job.bank,
        query_types=job.query_types,
        config=config,
        query_config=job.query_config,
        device=job.device,
        encoder=job.encoder,
        relevancy_dir=out / "relevancy" if job.relevancy else None,
        on_ready=on_ready,
        engine=engine,
    )
    result.notes.extend(job.notes)
    if with_3d:
        from ..data.labels import read_label_dir
        from .protocol3d import evaluate_protocol3d

        result.protocol3d = evaluate_protocol3d(
            engine, read_label_dir(job.labels), modes=result.modes, config=_protocol3d_config(job), label_dir=job.labels
        ).to_dict()
    if job.budget:
        from .budget import loss_budget

        result.budget = loss_budget(
            job.run_dir,
            job.labels,
            scene=job.scene,
            bank=job.bank,
            query_types=job.query_types,
            config=config,
            query_config=job.query_config,
            device=job.device,
            field_result=result,
            engine=engine,
        )
    write_eval_outputs(result, out, compare=job.compare)
    for line in mode_summary_lines(result):
        log(line)
    if result.protocol3d:
        for line in protocol3d_summary_lines(result.protocol3d):
            log(line)
    if result.budget:
        from .budget import budget_table

        log("loss budget:\n" + budget_table(result.budget))
    for note in result.notes:
        log(f"note: {note}")
    log(f"eval: {result.scores[result.modes[0]]['exact'].num_pairs} pairs in {result.seconds:.1f} s -> {out}")
    return result


def _labels_3d(job: EvalJob, engine, out: Path, on_ready: Callable[[], None], log: Log):
    """OpenGaussian's 3D protocol: Gaussians selected in 3D, rendered into each labelled view."""
    from ..data.labels import read_label_dir
    from .protocol3d import evaluate_protocol3d, write_protocol3d_outputs
    from .reports import protocol3d_summary_lines

    res = evaluate_protocol3d(
        engine,
        read_label_dir(job.labels),
        modes=job.modes,
        config=_protocol3d_config(job),
        label_dir=job.labels,
        on_ready=on_ready,
    )
    res.notes.extend(job.notes)
    write_protocol3d_outputs(res, out)
    for line in protocol3d_summary_lines(res.to_dict()):
        log(line)
    for note in res.notes:
        log(f"note: {note}")
    log(f"eval: {res.scores[res.modes[0]].num_pairs} pairs (3D protocol) in {res.seconds:.1f} s -> {out}")
    return res


def _ovs3d(job: EvalJob, engine, out: Path, on_ready: Callable[[], None], log: Log):
    """The 3D-OVS protocol on labels in the 3D-OVS layout."""
    from .ovs3d import evaluate_run_ovs3d, write_ovs3d_outputs
    from .reports import ovs3d_summary_lines

    data = evaluate_run_ovs3d(
        engine,
        job.labels,
        modes=None if job.modes is None else list(job.modes),
        prediction=job.ovs_prediction,
        progress=job.progress,
        on_ready=on_ready,
    )
    write_ovs3d_outputs(data, out)
    for line in ovs3d_summary_lines(data):
        log(line)
    for note in data["notes"]:
        log(f"note: {note}")
    log(
        f"eval: 3D-OVS, {len(data['views'])} views x {len(data['classes'])} classes in {data['seconds']:.1f} s -> {out}"
    )
    return data


_FIELD_INPUTS = ("--compare", "--budget", "--query-types", "--bank", "--skip-missing-frames", "--rescale-labels")
TWO_D = EvalProtocol(
    "2d",
    "LangSplat's LERF-OVS protocol on rendered relevancy maps (default for LERF-OVS labels)",
    _FIELD_INPUTS,
    False,
    False,
    _labels_2d,
)
THREE_D = EvalProtocol(
    "3d",
    "Gaussians selected in 3D and rendered into each labelled view (OpenGaussian's protocol: "
    "mIoU, mAcc@0.25, localization)",
    ("--skip-missing-frames", "--rescale-labels"),
    True,
    True,
    _labels_3d,
)
BOTH = EvalProtocol(
    "both",
    "the two side by side in one eval.json / eval.md",
    _FIELD_INPUTS,
    True,
    True,
    lambda job, engine, out, on_ready, log: _labels_2d(job, engine, out, on_ready, log, with_3d=True),
)
OVS3D = EvalProtocol(
    "3d-ovs", "the 3D-OVS protocol (default when --labels is in the 3D-OVS layout)", (), True, False, _ovs3d
)

PROTOCOLS: dict[str, EvalProtocol] = {p.name: p for p in (TWO_D, THREE_D, BOTH, OVS3D)}


def get_protocol(name: str) -> EvalProtocol:
    if name not in PROTOCOLS:
        raise InputError(None, f"unknown protocol {name!r}; choose from {', '.join(PROTOCOLS)}")
    return PROTOCOLS[name]


def choose_protocol(name: Optional[str], labels: Path) -> EvalProtocol:
    """``name``'s protocol, or the one the labels' layout implies: 3D-OVS for labels in the
    3D-OVS layout, else LangSplat's 2D protocol. Labels in the 3D-OVS layout take only it."""
    from .ovs3d import ovs3d_labels_path

    ovs = ovs3d_labels_path(labels) is not None
    protocol = get_protocol(name) if name else (OVS3D if ovs else TWO_D)
    if ovs and protocol is not OVS3D:
        raise InputError(
            labels, f"labels in the 3D-OVS layout are scored by --protocol {OVS3D.name}, not {protocol.name}"
        )
    return protocol
