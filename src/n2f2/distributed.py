"""Where independent tasks run: one after another in this process (``--executor serial``), or
as Ray tasks on a local Ray instance or a Ray cluster (``--executor ray``).

This module knows nothing about scenes or banks: callers hand :meth:`map` a picklable
function and a list of items, and get ``(item index, result)`` pairs back as tasks finish.
Only the calling process (the driver) writes files, so outputs stay resumable whatever order
tasks finish in. Ray is imported only when a Ray executor first runs a task, so the serial
path never imports it; ``pip install 'n2f2[ray]'`` installs it.

A task raising :class:`~n2f2.errors.N2F2Error` (bad input) yields a :class:`TaskFailure`
instead of its result, so the other tasks go on; any other exception (a bug) propagates.
A worker process that dies is Ray's business: the task is retried up to ``max_retries`` times.
"""

from __future__ import annotations

import argparse
import importlib
import os
from dataclasses import dataclass
from typing import Any, Callable, Hashable, Iterator, Optional, Sequence

from .errors import InputError, N2F2Error
from .heap import keep_freed_blocks
from .validate import positive_float

EXECUTORS = ("serial", "ray")
RAY_EXTRA = "install the extra: pip install 'n2f2[ray]'"
MAX_RETRIES = 3  # retries of a task whose worker process died (Ray's default for tasks)


@dataclass(frozen=True)
class TaskFailure:
    """A task that failed on bad input: the input it names (or None) and what is wrong."""

    path: Optional[str]
    problem: str

    @staticmethod
    def of(error: N2F2Error) -> "TaskFailure":
        if isinstance(error, InputError):
            return TaskFailure(None if error.path is None else str(error.path), error.problem)
        return TaskFailure(None, str(error))

    def error(self) -> InputError:
        return InputError(self.path, self.problem)

    def __str__(self) -> str:
        return str(self.error())


def _run_task(fn: Callable[[Any], Any], item: Any) -> Any:
    """Body of every task (serial or Ray): bad input becomes a :class:`TaskFailure` value, so
    it crosses process boundaries as data and Ray does not retry it. A Ray worker is a batch
    process, as the command line that starts a serial run is (:func:`n2f2.heap.keep_freed_blocks`)."""
    keep_freed_blocks()
    try:
        return fn(item)
    except N2F2Error as e:
        return TaskFailure.of(e)


class SerialExecutor:
    """Tasks run one after another in this process."""

    name = "serial"

    def __enter__(self) -> "SerialExecutor":
        return self

    def __exit__(self, *exc) -> None:
        pass

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        """``(k, fn(items[k]))`` in order; a bad input yields ``(k, TaskFailure)``."""
        for k, item in enumerate(items):
            yield k, _run_task(fn, item)


def import_ray():
    """The ``ray`` module, or an :class:`InputError` saying how to install it."""
    try:
        import ray
    except ImportError:
        raise InputError(None, f"--executor ray needs Ray; {RAY_EXTRA}") from None
    return ray


def check_ray_address(address: str, timeout: float = 5.0) -> None:
    """``auto``, ``ray://...`` (Ray Client), or a ``HOST:PORT`` that accepts connections:
    ``ray.init`` waits minutes on an address nobody listens on, so it is tried first."""
    import socket

    if address == "auto" or address.startswith("ray://"):
        return
    host, _, port = address.rpartition(":")
    if not host or not port.isdigit():
        raise InputError(None, f"--ray-address must be 'auto' or HOST:PORT of a Ray head node, got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise InputError(
            None,
            f"no Ray head node answers at {address} ({e}); start one with "
            "`ray start --head --port=PORT` (docs/distributed.md)",
        ) from None


def _init_local_ray(ray, num_cpus: Optional[int]) -> None:
    """Start a local Ray instance whose servers all listen on 127.0.0.1 only.

    Ray binds its servers (GCS, raylet, workers, agents, metrics) to loopback when the node
    address is loopback, but ``ray.init`` swaps a loopback ``_node_ip_address`` for this
    machine's network address unless ``ray_constants.ENABLE_RAY_CLUSTER`` is off (as it is on
    macOS and Windows). It is turned off for this call only: joining a cluster and the
    processes Ray starts (given the node address on their command lines) are unaffected."""
    try:
        constants: Any = importlib.import_module("ray._private.ray_constants")
    except ImportError:  # a Ray without it: its servers listen on all interfaces
        constants = None
    enabled = getattr(constants, "ENABLE_RAY_CLUSTER", None)
    if enabled is not None:
        constants.ENABLE_RAY_CLUSTER = False
    try:
        ray.init(address="local", num_cpus=num_cpus, include_dashboard=False, _node_ip_address="127.0.0.1")
    finally:
        if enabled is not None:
            constants.ENABLE_RAY_CLUSTER = enabled


class RayExecutor:
    """Tasks run as Ray tasks, one per item, each asking for ``cpus_per_task`` CPUs and
    ``gpus_per_task`` GPUs (Ray sets ``CUDA_VISIBLE_DEVICES`` and ``OMP_NUM_THREADS`` of the
    worker to match).

    ``address=None`` starts a local Ray instance for the duration of the ``with`` block
    (``num_cpus``, default all cores; no dashboard; its servers listen on 127.0.0.1 only,
    :func:`_init_local_ray`); ``"auto"`` or
    ``"HOST:PORT"`` joins a running cluster. When Ray is already initialised in this process,
    that instance is used and left running. Ray starts on the first :meth:`map`, so a command
    with nothing left to do does not pay its start-up."""

    name = "ray"

    def __init__(
        self,
        address: Optional[str] = None,
        *,
        num_cpus: Optional[int] = None,
        cpus_per_task: float = 1,
        gpus_per_task: float = 0,
        max_retries: int = MAX_RETRIES,
    ) -> None:
        self.ray = import_ray()  # fail before any work when Ray is missing
        if address is not None:
            check_ray_address(address)
        self.address = address
        self.num_cpus = num_cpus
        self.cpus_per_task = cpus_per_task
        self.gpus_per_task = gpus_per_task
        self.max_retries = max_retries
        self._started = False

    def __enter__(self) -> "RayExecutor":
        return self

    def __exit__(self, *exc) -> None:
        if self._started:
            self.ray.shutdown()
            self._started = False

    def start(self) -> None:
        """Connect to (or start) Ray unless this process already is connected."""
        ray = self.ray
        if ray.is_initialized():
            return
        try:
            if self.address is None:
                _init_local_ray(ray, self.num_cpus or os.cpu_count())
            else:
                ray.init(address=self.address)
        except (ConnectionError, ValueError, RuntimeError) as e:
            where = "a local Ray instance" if self.address is None else f"the Ray cluster at {self.address}"
            raise InputError(None, f"cannot start or join {where} ({e})") from None
        self._started = True

    def _check_feasible(self) -> None:
        """Ray queues a task no node can hold for ever: refuse it up front."""
        want = {"CPU": self.cpus_per_task, "GPU": self.gpus_per_task}
        nodes = [n.get("Resources", {}) for n in self.ray.nodes() if n.get("Alive")]
        if not any(all(r.get(k, 0) >= v for k, v in want.items() if v) for r in nodes):
            need = " and ".join(f"{v:g} {k}" for k, v in want.items() if v)
            have = "; ".join(f"{r.get('CPU', 0):g} CPU, {r.get('GPU', 0):g} GPU" for r in nodes) or "no nodes"
            raise InputError(
                None,
                f"no node of the Ray cluster has {need} for one task (nodes: {have}); lower "
                "--ray-cpus-per-task, or start nodes with `ray start ... --num-gpus N` for --device cuda",
            )

    def map(self, fn: Callable[[Any], Any], items: Sequence[Any]) -> Iterator[tuple[int, Any]]:
        """``(k, fn(items[k]))`` in completion order; a bad input yields ``(k, TaskFailure)``.
        When the caller stops iterating (or raises), tasks not started are dropped and a running
        task is killed with its worker process. Ray's gentler cancel raises KeyboardInterrupt in
        the task, wherever it is: in the middle of an import (torch, transformers) it leaves the
        worker's modules half initialised, and every later task Ray gives that worker fails."""
        if not items:
            return
        self.start()
        self._check_feasible()
        ray = self.ray
        task = ray.remote(_run_task).options(
            num_cpus=self.cpus_per_task,
            num_gpus=self.gpus_per_task,
            max_retries=self.max_retries,
            retry_exceptions=False,
        )
        fn_ref = ray.put(fn)
        pending = {task.remote(fn_ref, item): k for k, item in enumerate(items)}
        try:
            while pending:
                done, _ = ray.wait(list(pending), num_returns=1)
                for ref in done:
                    k = pending.pop(ref)
                    yield k, ray.get(ref)
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)


Executor = SerialExecutor | RayExecutor


# ----------------------------------------------------------------------------- per-worker state
_WORKER_STATE: dict[Hashable, Any] = {}


def worker_state(key: Hashable, build: Callable[[], Any]) -> Any:
    """``build()`` once per process for ``key``: a Ray worker runs many tasks of one command and
    loads its models once. Only the latest key is kept, so a worker reused by another command
    frees what the previous one built."""
    if key not in _WORKER_STATE:
        _WORKER_STATE.clear()
        _WORKER_STATE[key] = build()
    return _WORKER_STATE[key]


# ----------------------------------------------------------------------------- command line
def add_executor_options(p: argparse.ArgumentParser, unit: str) -> None:
    """``--executor``, ``--ray-address`` and ``--ray-cpus-per-task`` (one task per ``unit``)."""
    p.add_argument(
        "--executor",
        choices=EXECUTORS,
        default="serial",
        help=f"serial: one {unit} after another in this process (default); ray: one Ray task per "
        f"{unit} (needs the ray extra: pip install 'n2f2[ray]'; see docs/distributed.md)",
    )
    p.add_argument(
        "--ray-address",
        metavar="ADDR",
        default=None,
        help="with --executor ray: 'auto' or HOST:PORT joins a running Ray cluster (its nodes must "
        "see the same scene and output folders); default: start a local Ray instance on "
        "all cores of this machine",
    )
    p.add_argument(
        "--ray-cpus-per-task",
        type=positive_float,
        default=1.0,
        metavar="N",
        help=f"with --executor ray: CPUs each {unit}'s task asks for (its torch threads; default 1)",
    )


def executor_from_args(args: argparse.Namespace, gpu: bool = False) -> Executor:
    """The executor the options ask for; ``gpu``: each Ray task asks for one GPU."""
    if args.executor != "ray":
        if args.ray_address is not None:
            raise InputError(None, "--ray-address needs --executor ray")
        return SerialExecutor()
    return RayExecutor(args.ray_address, cpus_per_task=args.ray_cpus_per_task, gpus_per_task=1 if gpu else 0)
