"""Register many pairs: a local process pool (default) or a Ray cluster, streamed and resumable.

    records = register_many([("a.ply", "b.ply"), ("b.ply", "c.ply")], output="results.jsonl")

Local workers are started by loky (BSD; joblib's executor): fork + exec of a fresh interpreter
that never re-runs the caller's script, so a script without an ``if __name__ == "__main__":``
guard, a notebook and ``python - <<EOF`` all work (multiprocessing's spawn re-imports the main
module in every worker, which kills them in such scripts while the parent waits for ever).

Each worker loads the model once (one :class:`~logdesc_rt.registration.Registrar`, its two
ONNX sessions with ``cores / workers`` onnxruntime threads) and registers the pairs it is
handed. Every pair gives one JSON record, written to ``output`` (JSON lines, one record a
line, flushed) as soon as it finishes. A pair that fails (unreadable file, degenerate cloud,
a worker that died) gives an error record; the run goes on. A pair the pipeline cannot register
(too few matches) is a result like any other: ``success`` false, with its ``reason``. With
``resume=True`` pairs whose record is already in ``output`` are skipped, so an interrupted run
continues where it stopped: a result, or an error the pair itself settles (a
:class:`~logdesc_rt.errors.RegistrationError` record of an older version). Other error records
(an unreadable file, a worker that died) are retried: the file may have been mended.

Record keys (the JSON-lines format):

- ``id``: the pair's id (given, or ``"SOURCE -> TARGET"`` for two paths, else ``"pair-000007"``
  from its position), ``source`` / ``target``: the paths, or null for in-memory arrays;
- ``ok``: true when the pipeline produced a pose. Then ``transformation`` (4 x 4 nested lists,
  source -> target frame), ``transformation_before_refinement``, ``success``, ``confidence``,
  ``reason`` (null for a success), ``fitness``, ``inlier_rmse`` (null without inliers),
  ``max_correspondence_distance``,
  ``correspondence_count``, ``pose_estimator``, ``refinement``, ``subsampled``, ``icp``,
  ``timings_s`` (seconds per stage);
- ``ok`` false: ``error`` = ``{"type": exception class name, "message": ...}``.

Determinism: every record but ``timings_s`` depends only on the pair, the options and the
seed, not on the backend or the number of workers (tests/test_batch.py holds 1 worker, 2
workers and Ray to the same records).

Clouds are sent to the workers once, not once per pair: a table of the distinct clouds
(paths, or arrays) goes to each local worker when it starts, and to Ray's object store
(``ray.put``) once per array; jobs carry only keys into that table. Paths are read by the
workers, so on a Ray cluster they must name files every node can read (a shared file system),
or pass arrays.
"""

from __future__ import annotations

import json
import os
from concurrent.futures import FIRST_COMPLETED, wait
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable, Iterator

import numpy as np

from .config import RuntimeConfig
from .errors import RegistrationError

BACKENDS: tuple[str, ...] = ("local", "ray")
# Keys of a record that depend on the machine's load, not on the pair: left out when records
# are compared across backends and worker counts.
TIMING_KEYS: tuple[str, ...] = ("timings_s",)
_FROM_CONFIG = "from-config"  # refine's default: the config's refinement (None means "no ICP")
_NATIVE_THREAD_VARIABLES = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")
# Error types a record keeps on resume (is_final): the verdicts of a pipeline that ran.
_SETTLED_ERRORS = frozenset({RegistrationError.__name__})


@dataclass(frozen=True)
class WorkerSpec:
    """What each worker needs to build its Registrar and run a pair, picklable.

    Attributes:
        threads: onnxruntime intra-op threads of this worker (>= 1).
        model_dir: the exported model's folder; None = the bundled model.
        config: the runtime configuration: None = the model's defaults, a dict = a partial
            one over them, or a RuntimeConfig (see :class:`~logdesc_rt.registration.Registrar`).
        register_options: keyword arguments of :meth:`Registrar.register` (estimator, refine,
            max_correspondence_distance, seed); only those the caller set.
    """

    threads: int
    model_dir: str | None = None
    config: RuntimeConfig | dict | None = None
    register_options: dict[str, Any] = field(default_factory=dict)

    def registrar(self):
        from .registration import Registrar

        return Registrar(self.model_dir, threads=self.threads, config=self.config)


@dataclass(frozen=True)
class PairJob:
    """One pair to register: its id and the keys of its two clouds in the cloud table.

    Attributes:
        pair_id: unique id of the pair (the record's ``id``).
        source_key, target_key: keys into the cloud table (path strings or ``"array-K"``).
        source_path, target_path: the paths as given, or None for arrays.
    """

    pair_id: str
    source_key: str
    target_key: str
    source_path: str | None
    target_path: str | None


def run_pair(registrar, spec: WorkerSpec, job: PairJob, source, target) -> dict:
    """Register one pair and return its record; never raises for a bad pair.

    Args:
        registrar: a loaded :class:`~logdesc_rt.registration.Registrar`.
        spec: the options (``spec.register_options`` are passed to ``registrar.register``).
        job: the pair's id and paths.
        source, target: the clouds, (N, 3) / (M, 3) arrays or paths.

    Returns:
        The pair's record (module docstring): ``ok`` true with the pose and its scores, or
        ``ok`` false with the error's type and message.
    """
    record: dict[str, Any] = {"id": job.pair_id, "source": job.source_path, "target": job.target_path}
    try:
        result = registrar.register(source, target, **spec.register_options)
    except Exception as error:  # one bad pair must not end the run: it becomes its record
        record.update(ok=False, error={"type": type(error).__name__, "message": str(error)})
        return record
    summary = result.to_dict()
    record["ok"] = True
    for key in (
        "transformation",
        "transformation_before_refinement",
        "success",
        "confidence",
        "reason",
        "fitness",
        "inlier_rmse",
        "max_correspondence_distance",
        "correspondence_count",
        "pose_estimator",
        "refinement",
        "subsampled",
        "icp",
        "timings_s",
    ):
        record[key] = summary[key]
    # Through JSON and back: the record in memory is the one in the file (NumPy scalars as
    # Python numbers, NaN as None), whichever backend made it.
    return json.loads(json.dumps(_json_safe(record), default=_numpy_scalar, allow_nan=False))


def _numpy_scalar(value):
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def comparable(record: dict) -> dict:
    """``record`` without the keys that depend on the machine's load (timings)."""
    return {key: value for key, value in record.items() if key not in TIMING_KEYS}


def is_final(record: dict) -> bool:
    """Whether a record needs no second run: a pose, or an error the pair itself settles.

    A RegistrationError (fewer than 3 matches, degenerate matches) is the pipeline's verdict
    on the clouds: running the pair again with the same options and seed repeats it, at the
    cost of a network pass. Any other error (file, worker, model) may not recur.
    """
    return bool(record.get("ok")) or record.get("error", {}).get("type") in _SETTLED_ERRORS


def read_records(path: str | os.PathLike) -> dict[str, dict]:
    """The records of a JSON-lines output file, by pair id (the last record of an id wins).

    A line that does not parse (a run killed in the middle of a write) is ignored.
    A missing file gives an empty dict.
    """
    records: dict[str, dict] = {}
    path = Path(path)
    if not path.exists():
        return records
    with path.open() as handle:
        for line in handle:
            line = line.strip()
            if not line:
                continue
            try:
                record = json.loads(line)
            except json.JSONDecodeError:
                continue
            if isinstance(record, dict) and "id" in record:
                records[str(record["id"])] = record
    return records


def register_many(
    pairs: Iterable,
    *,
    workers: int | None = None,
    backend: str = "local",
    address: str | None = None,
    output: str | os.PathLike | None = None,
    resume: bool = True,
    progress: bool | None = None,
    on_record: Callable[[dict], None] | None = None,
    threads_per_worker: int | None = None,
    model_dir: str | os.PathLike | None = None,
    config: RuntimeConfig | dict | None = None,
    estimator: str | None = None,
    refine: str | None = _FROM_CONFIG,
    max_correspondence_distance: float | None = None,
    seed: int | None = None,
) -> list[dict]:
    """Register many pairs with one model load per worker; stream, resume, never lose a run.

    Args:
        pairs: iterable of ``(source, target)`` or ``(pair_id, source, target)`` tuples, or
            mappings with keys ``source``, ``target`` and optionally ``id``. Clouds are (N, 3)
            arrays or point-cloud file paths (any format :func:`~logdesc_rt.read_point_cloud`
            reads). Ids must be unique; by default a pair of paths is ``"SOURCE -> TARGET"``,
            any other pair ``"pair-{position:06d}"``.
        workers: local processes or Ray actors; None = every core (local) or every CPU of the
            cluster (Ray), at most one per pair to run. ``workers=0`` (local only) runs in
            this process, no pool.
        backend: "local" (a process pool) or "ray" (one actor per worker; needs
            ``pip install "logdesc-rt[ray]"``).
        address: Ray only: the cluster to join (e.g. ``"ray://head:10001"`` or ``"auto"``);
            None starts a local Ray instance unless one is already initialised.
        output: JSON-lines file the records are appended to as they finish (created if
            missing); None keeps them in memory only.
        resume: skip pairs whose record in ``output`` is final (:func:`is_final`: a pose, or
            a RegistrationError); other error records are run again. False starts the file
            afresh.
        progress: show a tqdm progress bar on stderr (None: when tqdm is installed and stderr
            is a terminal).
        on_record: called with each new record as it finishes (in completion order).
        threads_per_worker: onnxruntime (and OpenMP / BLAS) threads per worker; None =
            cores / workers (local) or cluster CPUs / workers (Ray), at least 1. Records are
            bit-identical across backends and worker counts at equal threads per worker; with
            different thread counts, floats differ by round-off (~1e-12 relative: summation
            order), discrete outputs (success, estimator, match count) not at all.
        model_dir: the exported model to load (None: the bundled one).
        config, estimator, refine, max_correspondence_distance, seed: as in
            :meth:`Registrar.register <logdesc_rt.registration.Registrar.register>`; ``refine``
            left out keeps the config's refinement.

    Returns:
        One record per pair, in the order of ``pairs`` (those skipped on resume read back
        from ``output``). Record keys: see the module docstring.

    Raises:
        ValueError: unknown backend, workers < 0, duplicate pair ids, a malformed pair.
        ImportError: backend "ray" without Ray installed.
    """
    if backend not in BACKENDS:
        raise ValueError(f"backend {backend!r}: expected one of {BACKENDS}")
    if workers is not None and (isinstance(workers, bool) or int(workers) != workers or workers < 0):
        raise ValueError(f"workers: {workers!r} must be an integer >= 0 (or None for every core)")
    if threads_per_worker is not None and (int(threads_per_worker) != threads_per_worker or threads_per_worker < 1):
        raise ValueError(f"threads_per_worker: {threads_per_worker!r} must be an integer >= 1")
    if workers == 0 and backend != "local":
        raise ValueError("workers=0 (run in this process) is for the local backend only")
    workers = None if workers is None else int(workers)
    threads_per_worker = None if threads_per_worker is None else int(threads_per_worker)
    jobs, clouds = plan_jobs(pairs)
    options: dict[str, Any] = {}
    if estimator is not None:
        options["estimator"] = estimator
    if refine != _FROM_CONFIG:
        options["refine"] = refine
    if max_correspondence_distance is not None:
        options["max_correspondence_distance"] = max_correspondence_distance
    if seed is not None:
        options["seed"] = seed
    model_dir = None if model_dir is None else str(model_dir)

    output_path = None if output is None else Path(output)
    done: dict[str, dict] = {}
    if output_path is not None:
        if resume:
            done = {key: record for key, record in read_records(output_path).items() if is_final(record)}
        else:
            output_path.write_text("")
    todo = [job for job in jobs if job.pair_id not in done]
    new_records: dict[str, dict] = {}

    with _RecordWriter(output_path) as writer, _progress_bar(len(todo), progress) as bar:

        def finished(record: dict) -> None:
            new_records[record["id"]] = record
            writer.write(record)
            bar(record)
            if on_record is not None:
                on_record(record)

        if todo:
            if backend == "ray":
                _run_ray(todo, clouds, workers, threads_per_worker, address, model_dir, config, options, finished)
            else:
                _run_local(todo, clouds, workers, threads_per_worker, model_dir, config, options, finished)
    return [new_records.get(job.pair_id) or done[job.pair_id] for job in jobs]


# ---------------------------------------------------------------------------- planning
def plan_jobs(pairs: Iterable) -> tuple[list[PairJob], dict[str, Any]]:
    """Turn the caller's pairs into jobs and a table of distinct clouds.

    Returns:
        (jobs, clouds): one :class:`PairJob` per pair, in order, and key -> cloud (a path
        string, or an (N, 3) array; one entry per distinct path or array object).

    Raises:
        ValueError: a malformed pair or a duplicate id.
    """
    jobs: list[PairJob] = []
    clouds: dict[str, Any] = {}
    array_keys: dict[int, str] = {}

    def key_of(cloud) -> tuple[str, str | None]:
        if isinstance(cloud, (str, os.PathLike)):
            path = os.fspath(cloud)
            clouds.setdefault(path, path)
            return path, path
        identity = id(cloud)
        if identity not in array_keys:
            array_keys[identity] = f"array-{len(array_keys)}"
            clouds[array_keys[identity]] = cloud
        return array_keys[identity], None

    seen: set[str] = set()
    for position, pair in enumerate(pairs):
        if isinstance(pair, dict):
            if "source" not in pair or "target" not in pair:
                raise ValueError(f"pair {position}: a mapping needs keys 'source' and 'target', got {sorted(pair)}")
            pair_id, source, target = pair.get("id"), pair["source"], pair["target"]
        elif isinstance(pair, (tuple, list)) and len(pair) in (2, 3):
            pair_id, source, target = (None, *pair) if len(pair) == 2 else pair
        else:
            raise ValueError(f"pair {position}: expected (source, target), (id, source, target) or a mapping")
        source_key, source_path = key_of(source)
        target_key, target_path = key_of(target)
        if pair_id is None:
            pair_id = (
                f"{source_path} -> {target_path}"
                if source_path is not None and target_path is not None
                else f"pair-{position:06d}"
            )
        pair_id = str(pair_id)
        if pair_id in seen:
            raise ValueError(f"pair {position}: duplicate pair id {pair_id!r}")
        seen.add(pair_id)
        jobs.append(PairJob(pair_id, source_key, target_key, source_path, target_path))
    return jobs, clouds


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


# ---------------------------------------------------------------------------- local backend
_WORKER: dict[str, Any] = {}  # the worker process's Registrar, spec and cloud table


def _init_worker(spec: WorkerSpec, clouds: dict[str, Any]) -> None:
    _WORKER["spec"] = spec
    _WORKER["clouds"] = clouds
    _WORKER["registrar"] = spec.registrar()


def _work(job: PairJob) -> dict:
    clouds = _WORKER["clouds"]
    return run_pair(_WORKER["registrar"], _WORKER["spec"], job, clouds[job.source_key], clouds[job.target_key])


def _run_local(todo, clouds, workers, threads, model_dir, config, options, finished) -> None:
    cores = available_cores()
    workers = min(cores if workers is None else workers, len(todo))
    if workers == 0:  # in this process
        spec = WorkerSpec(threads=threads or cores, model_dir=model_dir, config=config, register_options=options)
        registrar = spec.registrar()
        for job in todo:
            finished(run_pair(registrar, spec, job, clouds[job.source_key], clouds[job.target_key]))
        return
    threads = threads or max(1, cores // workers)
    spec = WorkerSpec(threads=threads, model_dir=model_dir, config=config, register_options=options)
    # loky: fork + exec (no fork of onnxruntime's or OpenBLAS's threads), and the workers never
    # import the caller's __main__; the thread limits reach the children before NumPy loads.
    from loky import ProcessPoolExecutor
    from loky.process_executor import BrokenProcessPool as LokyBrokenPool

    environment = {name: str(threads) for name in _NATIVE_THREAD_VARIABLES}
    with ProcessPoolExecutor(
        max_workers=workers, initializer=_init_worker, initargs=(spec, clouds), env=environment
    ) as pool:
        pending = {pool.submit(_work, job): job for job in todo}
        while pending:
            done, _ = wait(pending, return_when=FIRST_COMPLETED)
            for future in done:
                job = pending.pop(future)
                try:
                    record = future.result()
                except (BrokenProcessPool, LokyBrokenPool) as error:
                    # A worker died (out of memory, a crash in native code): the pairs it held
                    # and those still queued get error records; a resumed run retries them.
                    record = _error_record(job, "WorkerCrashed", f"a worker process died: {error}")
                except Exception as error:  # e.g. the model failed to load in the worker
                    record = _error_record(job, type(error).__name__, str(error))
                finished(record)


def _error_record(job: PairJob, kind: str, message: str) -> dict:
    return {
        "id": job.pair_id,
        "source": job.source_path,
        "target": job.target_path,
        "ok": False,
        "error": {"type": kind, "message": message},
    }


# ---------------------------------------------------------------------------- Ray backend
class _RayWorker:
    """A Ray actor's body: one Registrar (two ONNX sessions) for the actor's life."""

    def __init__(self, spec: WorkerSpec):
        self.spec = spec
        self.registrar = spec.registrar()

    def run(self, job: PairJob, source, target) -> dict:
        # source / target arrive as arrays: Ray resolves top-level ObjectRef arguments,
        # zero-copy (read-only) from the object store.
        return run_pair(self.registrar, self.spec, job, source, target)


def _run_ray(todo, clouds, workers, threads, address, model_dir, config, options, finished) -> None:
    try:
        import ray
    except ImportError as error:
        raise ImportError('backend="ray" needs Ray: pip install "logdesc-rt[ray]"') from error

    started_here = not ray.is_initialized()
    if started_here:
        # A new local instance stays quiet; joining a cluster takes the cluster's settings
        # (Ray Client, "ray://...", accepts few init options).
        ray.init(address=address) if address is not None else ray.init(include_dashboard=False, log_to_driver=False)
    try:
        cluster_cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        workers = min(cluster_cpus if workers is None else workers, len(todo))
        threads = threads or max(1, cluster_cpus // workers)
        spec = WorkerSpec(threads=threads, model_dir=model_dir, config=config, register_options=options)
        actor_class = ray.remote(num_cpus=threads)(_RayWorker)
        actors = [actor_class.remote(spec) for _ in range(workers)]
        # Each array once into the object store; paths travel as they are.
        table = {
            key: (cloud if isinstance(cloud, str) else ray.put(np.asarray(cloud))) for key, cloud in clouds.items()
        }
        queue = list(reversed(todo))
        running: dict[Any, tuple[PairJob, Any]] = {}

        def submit(actor) -> None:
            job = queue.pop()
            reference = actor.run.remote(job, table[job.source_key], table[job.target_key])
            running[reference] = (job, actor)

        for actor in actors:
            if queue:
                submit(actor)
        while running:
            ready, _ = ray.wait(list(running), num_returns=1)
            job, actor = running.pop(ready[0])
            try:
                record = ray.get(ready[0])
            except Exception as error:  # the actor died (RayActorError) or its task failed
                record = _error_record(job, type(error).__name__, str(error))
                if "ActorDied" in type(error).__name__ or "RayActorError" in type(error).__name__:
                    actor = actor_class.remote(spec)  # replace the dead actor
            finished(record)
            if queue:
                submit(actor)
    finally:
        if started_here:
            ray.shutdown()


# ---------------------------------------------------------------------------- output
class _RecordWriter:
    """Appends records to a JSON-lines file, one flushed line each (no file: does nothing)."""

    def __init__(self, path: Path | None):
        self.path = path
        self.handle = None

    def __enter__(self) -> "_RecordWriter":
        if self.path is not None:
            needs_newline = False
            if self.path.exists() and self.path.stat().st_size > 0:
                with self.path.open("rb") as existing:
                    existing.seek(-1, os.SEEK_END)
                    needs_newline = existing.read(1) != b"\n"
            self.handle = self.path.open("a")
            if needs_newline:  # a run killed mid-line left a partial record: start a new line
                self.handle.write("\n")
        return self

    def write(self, record: dict) -> None:
        if self.handle is not None:
            self.handle.write(json.dumps(_json_safe(record), allow_nan=False) + "\n")
            self.handle.flush()

    def __exit__(self, *exc) -> None:
        if self.handle is not None:
            self.handle.close()


def _json_safe(value):
    """``value`` with NaN / inf floats as None (JSON has neither), recursively."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, dict):
        return {key: _json_safe(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_safe(item) for item in value]
    return value


@contextmanager
def _progress_bar(total: int, enabled: bool | None) -> Iterator[Callable[[dict], None]]:
    """A callable that advances a tqdm bar by one record (a no-op without tqdm / when off)."""
    import sys

    try:
        from tqdm import tqdm
    except ImportError:
        tqdm = None
    if enabled is None:
        enabled = tqdm is not None and sys.stderr.isatty()
    if not enabled or tqdm is None or total == 0:
        yield lambda record: None
        return
    failures = 0
    with tqdm(total=total, unit="pair", desc="registering") as bar:

        def advance(record: dict) -> None:
            nonlocal failures
            failures += 0 if record.get("ok") else 1
            bar.set_postfix(errors=failures, refresh=False)
            bar.update(1)

        yield advance
