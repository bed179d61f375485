"""All-vs-all dataset runs (paper §4): parallel pairs, a resumable SQLite store, distance matrices D(β) and D(∞).

``run_all_vs_all(shapes, out)`` compares every unordered pair of shapes (and, for partial transport, every
shape with itself, which Eq. 27 needs) and commits each finished pair at once to ``out/wpot.sqlite``:

* table ``run``: the parameters (JSON) and their hash, the shared WKS energy grid, the wpot version;
* table ``shapes``: index, name, source path, content fingerprint, vertex count;
* table ``labels``: (shape, level, label), from file names (level "class") and/or a CSV;
* table ``pairs``: one row per pair (i ≤ j): the raw energy U (balanced: transport cost, Eq. 6; partial:
  the objective of Eq. 17), the distance (U, or SU of Eq. 27 once both self-comparisons are in; 0 on the
  diagonal), the per-β history ``[[β, U_β], ...]`` as JSON, converged flag, Newton/linear iteration
  counts, seconds, worker;
* table ``computations``: one row per pair computation ever committed (so a test can check that no pair
  was computed twice), and ``failures`` for pairs that raised.

The database runs in WAL mode and only the coordinating process writes to it. A killed run loses at most
the pairs in flight: rerunning the same command resumes, skipping every committed pair. Rerunning with
other parameters or another shape list raises `RunMismatchError`; a shape file whose content changed since
the run began is refused by name (`RunMismatchError` at the start; a pair whose worker reads a changed file
fails and is recorded in ``failures``). One run folder has one coordinator at a time: `run_all_vs_all` holds
an exclusive lock on ``out/wpot.lock`` (`fcntl.flock`, released by the OS when the process ends, however it
ends), and a second run on the same folder raises `RunLockedError` at once rather than computing pairs twice.
A store that SQLite cannot read (truncated, overwritten) raises `CorruptRunError` naming the file; it is
never read as an empty or partial run.

A run stopped by Ctrl-C (a `KeyboardInterrupt`; under the ``wpot`` command also SIGTERM, see `wpot.stopping`)
stops at once: its own process pool's workers are killed, a local Dask cluster's workers closed, and the pairs
they were computing dropped, rather than waited for; every committed pair stays, and it raises
`wpot.stopping.Interrupted` saying what was stopped and how many pairs are stored. The workers ignore SIGINT (a
terminal's Ctrl-C reaches the whole process group; the coordinator decides) and exit when the coordinator is gone.

Execution is pluggable: ``jobs=1`` runs pairs inline; ``jobs>1`` uses a `ProcessPoolExecutor` (spawned
processes, safe with CUDA); any `concurrent.futures.Executor` can be passed instead, e.g. a Dask
cluster's ``client.get_executor()``. Workers receive self-contained tasks (mesh path or arrays, settings,
energy grid) and share an on-disk signature cache in ``out/cache``.

Dask (``scheduler=`` / ``wpot all-vs-all --scheduler``; needs ``pip install 'wpot[cluster]'``):

* ``scheduler="local"`` starts an embedded `distributed.LocalCluster` of ``jobs`` single-threaded worker
  processes; ``scheduler="tcp://host:port"`` uses a running cluster (``dask scheduler`` + ``dask worker``).
  Without ``scheduler`` nothing changes and Dask is never imported.
* The coordinator (this process) is the only writer of the store. Each pair is one Dask task; when a worker
  dies mid-pair, the scheduler hands its tasks to another worker, so the pair is computed again and only
  that pair's work is lost. A pair whose task kills its worker more than
  ``distributed.scheduler.allowed-failures`` times (Dask's default: 3) comes back as ``KilledWorker`` and is
  recorded in ``failures``, like a pair that raised; the run goes on, and rerunning the command retries it.
  Each future yields one result and `RunStore.commit` ignores a pair already stored, so a pair is committed
  once (the ``computations`` table shows it).
* Each worker picks its own Warp device when ``device`` is None (`choose_worker_device`): ``$WPOT_DEVICE``
  if set on the worker; else ``cpu`` on a worker without CUDA; else ``cuda:0`` when the worker's
  ``CUDA_VISIBLE_DEVICES`` is set (launchers such as dask-cuda give each worker its own GPU first in that
  list); else ``cuda:<rank mod n_gpus>`` from the worker's name (`LocalCluster` names its workers 0, 1, ...;
  ``dask worker --name host --nworkers 4`` gives host-0 ... host-3); else Warp's default device. The
  device a pair ran on is stored with its worker (``host:pid@device``). An explicit ``device`` is used by
  every worker.
* Workers read the meshes by path and share the signature cache through the run folder (or
  ``$WPOT_CACHE_DIR``), so on several machines the dataset and the run folder must be on a filesystem that
  every worker sees at the same path.
"""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import dataclasses
import os
import signal
import warnings
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping, Sequence

from wpot.mesh import Mesh, repair_mesh, repair_mode, repair_setting
from wpot.runs.shapes import discover_shapes, warn_repeated_shapes
from wpot.runs.store import RunMismatchError, RunStore, run_lock
from wpot.runs.workers import dask_executor, fit_input_of, pair_task, shape_task, signatures_of
from wpot.stopping import Interrupted, check_stop, pool_worker_setup, worker_context

__all__ = ["run_all_vs_all"]

def run_all_vs_all(
    shapes: str | Path | Sequence[str | Path | Mesh],
    out: str | Path,
    *,
    signature: str = "wks",
    transport: str = "balanced",
    jobs: int | None = 1,
    executor: cf.Executor | None = None,
    scheduler: str | None = None,
    labels: str | Path | Mapping[str, Mapping[str, str]] | None = None,
    device: str | None = None,
    progress: Any = True,
    max_pairs: int | None = None,
    config: Any = None,
    repair: bool | str = False,
    **comparer_options: Any,
) -> RunStore:
    """Compare every pair of ``shapes`` and store the results in the run folder ``out`` (resumable).

    Parameters
    ----------
    shapes : folder, list file, or sequence of paths / meshes (see `discover_shapes`)
    out : run folder; created if needed. An existing run with the same parameters and shapes is resumed.
    signature, transport, **comparer_options : as `wpot.comparison.Comparer` (max_vertices, mass_penalty,
        n_eigen, n_energies, ldsift_K, solver_options, ...). ``cache_dir`` (the signature and spectrum
        cache, shared by runs over the same shapes) defaults to ``$WPOT_CACHE_DIR``, else ``out/cache``.
    config : a `wpot.config.ComparisonConfig` instead of those keywords
    jobs : worker processes when ``executor`` is None (1: inline in this process; None: all CPU cores);
        with ``scheduler="local"``, the number of Dask workers. The workers are spawned, so a script that
        calls this with ``jobs != 1`` must do so under ``if __name__ == "__main__":`` (notebooks need nothing)
    executor : any `concurrent.futures.Executor` (e.g. a Dask ``client.get_executor()``); overrides ``jobs``
    scheduler : run the tasks on Dask (see `dask_executor`): ``"local"`` (an embedded `LocalCluster` of
        ``jobs`` processes) or a scheduler address ``"tcp://host:port"``. None (default): no Dask.
    labels : a label CSV (`wpot.datasets.read_label_csv`: a ``name`` column and one column per level); its
        first column is also level "class". Without it, "class" comes from the file names.
    device : Warp device every worker uses (None: Warp's default; on Dask, each worker's own choice,
        see `choose_worker_device`)
    progress : a `tqdm.auto` bar for every phase (reading the meshes, fitting the signature, the signatures, the
        pairs with their rate and ETA) on standard error: True, False, or a `wpot.progress.Progress`
    max_pairs : stop after committing this many new pairs (for tests and partial runs)
    repair : repair every mesh with `wpot.Mesh.cleaned` before it is used, here and in the workers: True (or
        "defects") removes zero-area and duplicate triangles and unreferenced vertices, "largest" also every
        connected component but the largest (`repair_mesh`); what was removed from which shape is stored with
        the run (``store.get("repairs")``: name -> what was removed) and reported. The shapes' stored
        fingerprints are those of the repaired meshes, so a resume must repair the same way.

    Returns
    -------
    RunStore : the open store; ``distance_matrix()`` and ``distance_matrices()`` read the results back.

    Raises
    ------
    RunLockedError : another process is running on ``out`` (one coordinator per run folder: `run_lock`)
    RunMismatchError : ``out`` holds a run with other parameters or shapes, or a shape file changed since
    CorruptRunError : ``out/wpot.sqlite`` is damaged
    Interrupted : (a `KeyboardInterrupt`) Ctrl-C or a signal stopped the run; its workers were stopped at once
        and every stored pair is kept (see the module docstring)

    The inputs are read and checked first, so a refused input leaves no run folder behind; the run folder's
    lock (`run_lock`) is then held for the rest of the run.
    """
    from wpot.progress import as_progress

    if scheduler is not None:
        if executor is not None:
            raise ValueError(f"give either executor or scheduler, not both (got scheduler={scheduler!r})")
        with dask_executor(scheduler, n_workers=jobs) as ex:
            return run_all_vs_all(
                shapes, out, signature=signature, transport=transport, jobs=jobs, executor=ex, scheduler=None, labels=labels,
                device=device, progress=progress, max_pairs=max_pairs, config=config, repair=repair,
                **comparer_options,
            )
    mode = repair_mode(repair)
    reporter = as_progress(progress)
    run = _read_inputs(shapes, out, labels=labels, config=config, signature=signature, transport=transport,
                       mode=mode, reporter=reporter, comparer_options=comparer_options)
    out = Path(out)
    with run_lock(out):
        store = _open_store(out, run, repair)
        todo = [t for t in store.tasks() if t not in store.done()]
        if not todo:
            return store
        own_pool = _process_pool(jobs) if executor is None else None
        interrupted = False
        try:
            _compute(store, own_pool or executor, todo, run, device, reporter, max_pairs)
        except KeyboardInterrupt as exc:  # Ctrl-C, or SIGTERM under the wpot command (wpot.stopping)
            interrupted = True
            raise _stopped(exc, store, own_pool, executor) from None
        finally:
            if own_pool is not None:
                own_pool.shutdown(wait=not interrupted, cancel_futures=True)
        return store


@dataclasses.dataclass
class _Inputs:
    """A run's inputs, every file read and checked before any work (`_read_inputs`)."""

    specs: list[Any]  # the shapes' `ShapeSpec`s, in order
    meshes: list[Mesh]  # their meshes (repaired when the run repairs them)
    repairs: dict[str, str]  # shape name -> what the repair removed
    config: Any  # the `ComparisonConfig`
    params: dict[str, Any]  # its run key (`ComparisonConfig.run_key`), stored with the run
    cache_dir: str
    mode: str  # the repair mode (`repair_mode`)

    @property
    def shape_rows(self) -> list[tuple[str, str | None, str, int]]:
        return [(s.name, s.path, m.fingerprint, m.n_vertices) for s, m in zip(self.specs, self.meshes)]

    @property
    def labels(self) -> dict[int, dict[str, str]]:
        return {k: dict(s.labels or {}) for k, s in enumerate(self.specs)}

    @property
    def task_specs(self) -> list[Any]:
        """What a task is given for each shape: (path, fingerprint), or the mesh itself when it has no file."""
        return [(s.path, m.fingerprint) if s.path is not None else m for s, m in zip(self.specs, self.meshes)]


def _read_inputs(shapes: Any, out: str | Path, *, labels: Any, config: Any, signature: str, transport: str,
                 mode: str, reporter: Any, comparer_options: dict[str, Any]) -> _Inputs:
    """The shapes, labels and configuration of a run, read and checked up front: fail before any work (and
    before the run folder is created)."""
    from wpot.comparison import check_mesh_size
    from wpot.config import ComparisonConfig

    if labels is not None and not isinstance(labels, (str, Path)):
        raise TypeError(f"labels must be a CSV path, got {type(labels).__name__}")
    specs = discover_shapes(shapes, labels=labels)
    out = Path(out)
    cache_dir = str(Path(comparer_options.pop("cache_dir", None) or os.environ.get("WPOT_CACHE_DIR") or out / "cache").resolve())
    if config is None:
        config = ComparisonConfig.from_keywords(signature=signature, transport=transport, **comparer_options)
    elif comparer_options or signature != "wks" or transport != "balanced":
        raise TypeError("give either config or the comparison keywords (signature, transport, ...), not both")
    params = config.run_key()

    meshes, repairs = [], {}
    bar = reporter.bar(len(specs), "reading meshes", "mesh")
    try:
        for s in specs:
            check_stop()
            m = s.load(warn=mode == "none")
            if mode != "none":
                m, _, what = repair_mesh(m, mode)
                if what:
                    repairs[s.name] = what
                    reporter.write(f"repaired {s.name}: removed {what}")
            check_mesh_size(m, config, f"shape {s.name!r}" + (f" ({s.path})" if s.path else ""))
            meshes.append(m)
            bar.update()
    finally:
        bar.close()
    warn_repeated_shapes([s.name for s in specs], [m.fingerprint for m in meshes])
    return _Inputs(specs, meshes, repairs, config, params, cache_dir, mode)


def _open_store(out: Path, run: _Inputs, repair: bool | str) -> RunStore:
    """The run folder's store, with the run recorded (a new run) or checked against it (a resumed one)."""
    mode = run.mode
    store = RunStore(out, create=True)
    stored_repair = store.get("repair", False)
    stored_mode = repair_mode(stored_repair)
    try:
        store.initialize(run.params, run.shape_rows, run.labels)
    except RunMismatchError as exc:
        if exc.differences or stored_mode == mode:
            raise
        raise RunMismatchError(f"{exc} The run was made with repair={stored_repair!r}; rerun with "
                               f"repair={stored_repair!r} to resume it.", folder=out,
                               differences=[("repair", stored_repair, repair_setting(mode))]) from None
    store.set("repair", repair_setting(mode))
    if mode != "none":
        store.set("repairs", run.repairs)
    return store


def _process_pool(jobs: int | None) -> cf.ProcessPoolExecutor | None:
    """The run's own pool of ``jobs`` spawned worker processes (None: every core), or None for ``jobs=1``
    (inline). Its workers ignore Ctrl-C from their start and exit with the coordinator (`wpot.stopping`'s
    `worker_context` and `pool_worker_setup`)."""
    if jobs is not None and jobs <= 1:
        return None
    return cf.ProcessPoolExecutor(max_workers=jobs or os.cpu_count(), mp_context=worker_context(),
                                  initializer=pool_worker_setup)


def _compute(store: RunStore, executor: cf.Executor | None, todo: list[tuple[int, int]], run: _Inputs,
             device: str | None, reporter: Any, max_pairs: int | None) -> None:
    """The run's work: fit the signature to the dataset when it needs it (once per run: paper §3.2, one WKS energy
    grid for the whole dataset, stored with the run), every needed shape's signatures, then the pairs."""
    from wpot.comparison import fit_phase
    from wpot.signatures import get_signature

    specs, task_specs = run.specs, run.task_specs
    # what every task needs to rebuild the comparer: the configuration, the signature's fitted state, the caches
    task_config = {"config": run.config.to_dict(), "state": store.signature_state(), "cache_dir": run.cache_dir,
                   "device": device, "repair": run.mode}
    stage = get_signature(run.config.signature)(run.config.signature_options)
    if stage.needs_fit and task_config["state"] is None:
        inputs = _map(executor, shape_task, [(fit_input_of, sp, task_config) for sp in task_specs],
                      fit_phase(stage), reporter, [s.name for s in specs])
        stage.fit_from(inputs)
        task_config["state"] = stage.state()
        store.set_signature_state(task_config["state"])
    needed = sorted({i for t in todo for i in t})
    _map(executor, shape_task, [(signatures_of, task_specs[i], task_config) for i in needed], "signatures",
         reporter, [specs[i].name for i in needed])
    _run_pairs(store, executor, todo, task_specs, task_config, reporter, max_pairs)


def _stopped(exc: KeyboardInterrupt, store: RunStore, pool: cf.ProcessPoolExecutor | None,
             executor: cf.Executor | None) -> Interrupted:
    """Stop a run that a signal interrupted, at once: kill the run's own worker processes (the pairs they were
    computing are dropped; waiting for them could take minutes), close the store. Returns the `Interrupted` to
    raise, saying what was stopped and what is kept."""
    if pool is not None:
        procs = list((getattr(pool, "_processes", None) or {}).values())
        # shut down first: the pool's manager thread then drops the cancelled futures before it sees its
        # workers die (Python 3.11's fails on a cancelled future when a worker dies)
        pool.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            with contextlib.suppress(Exception):
                p.kill()
        for p in procs:
            p.join(timeout=5)
        how = f"its {len(procs)} worker processes were stopped and the pairs they were computing dropped"
    elif executor is None:
        how = "the pair being computed was dropped"
    else:
        how = getattr(executor, "stop_words", "the pairs in flight were cancelled and dropped")
    try:
        n_done, n_total = len(store.done()), len(store.tasks())
        kept = f"{n_done} of {n_total} pairs stored in {store.folder}"
    except Exception:  # the store cannot be read now: say nothing about it
        kept = f"the pairs stored in {store.folder} are kept"
    finally:
        store.close()
    detail = f"{how}; {kept}; rerun the same command to resume the run"
    return Interrupted(getattr(exc, "signum", signal.SIGINT), detail)


def _completed(executor: cf.Executor, calls: Iterable[tuple[Any, Any, tuple]]) -> Iterator[tuple[Any, cf.Future]]:
    """Submit ``fn(*args)`` for each (key, fn, args) and yield (key, future) as they finish.

    An executor with ``max_in_flight()`` (`DaskExecutor`) gets no more tasks than that at a time (asked
    again every second, as workers come and go); others get every task at once. A finished future is
    dropped as soon as it has been yielded, so a cluster does not keep (or recompute) its result."""
    limit = getattr(executor, "max_in_flight", None)
    pending: dict[cf.Future, Any] = {}
    calls = iter(calls)
    exhausted = False
    try:
        if limit is None:
            for key, fn, args in calls:
                pending[executor.submit(fn, *args)] = key
            for f in cf.as_completed(list(pending)):
                yield pending.pop(f), f
            return
        while True:
            check_stop()
            cap = limit()
            while not exhausted and len(pending) < cap:
                try:
                    key, fn, args = next(calls)
                except StopIteration:
                    exhausted = True
                    break
                pending[executor.submit(fn, *args)] = key
            if not pending:
                return
            done, _ = cf.wait(list(pending), timeout=1.0, return_when=cf.FIRST_COMPLETED)
            for f in done:
                yield pending.pop(f), f
    finally:
        for f in pending:  # max_pairs reached, or the coordinator stopped: the rest is not needed
            f.cancel()


def _map(executor: cf.Executor | None, fn: Any, arglist: list[tuple], what: str, progress: Any,
         names: Sequence[str]) -> list[Any]:
    """Run `shape_task` (``fn`` is it) for each args (inline or on the executor), with a progress bar; returns
    the values in the order of ``arglist``, and says each task's warnings as they arrive, prefixed with the
    name of its shape (``names``, one per args)."""
    bar = progress.bar(len(arglist), what, "shape")

    def take(k: int, told: tuple[Any, list[tuple[type, str]]]) -> Any:
        check_stop()
        value, said = told
        for category, message in said:
            warnings.warn(f"{names[k]}: {message}", category, stacklevel=3)
        bar.update()
        return value

    try:
        if executor is None:
            return [take(k, fn(*a)) for k, a in enumerate(arglist)]
        results: list[Any] = [None] * len(arglist)
        with contextlib.closing(_completed(executor, ((k, fn, a) for k, a in enumerate(arglist)))) as finished:
            for k, f in finished:
                results[k] = take(k, f.result())
        return results
    finally:
        bar.close()


def _run_pairs(store: RunStore, executor, todo, task_specs, config, progress: Any, max_pairs: int | None) -> None:
    total = len(store.tasks())
    bar = progress.bar(total, "pairs", "pair", initial=total - len(todo), leave=True)
    n_new = 0

    def handle(i: int, j: int, fut_or_rec: Any) -> None:
        nonlocal n_new
        check_stop()
        try:
            rec = fut_or_rec.result() if isinstance(fut_or_rec, cf.Future) else fut_or_rec
        except Exception as exc:  # a failing pair is recorded and the run goes on
            store.record_failure(i, j, f"{type(exc).__name__}: {exc}")
            bar.write(f"pair ({i}, {j}) failed: {type(exc).__name__}: {exc}")
            return
        if store.commit(rec):
            n_new += 1
        bar.update()

    try:
        if executor is None:
            for i, j in todo:
                if max_pairs is not None and n_new >= max_pairs:
                    break
                check_stop()
                try:
                    rec = pair_task(i, j, task_specs[i], task_specs[j], config)
                except Exception as exc:
                    store.record_failure(i, j, f"{type(exc).__name__}: {exc}")
                    bar.write(f"pair ({i}, {j}) failed: {type(exc).__name__}: {exc}")
                    continue
                handle(i, j, rec)
        else:
            calls = (((i, j), pair_task, (i, j, task_specs[i], task_specs[j], config)) for i, j in todo)
            with contextlib.closing(_completed(executor, calls)) as finished:  # closing cancels the rest
                for (i, j), f in finished:
                    handle(i, j, f)
                    if max_pairs is not None and n_new >= max_pairs:
                        break
    finally:
        bar.close()
    fails = store.failures()
    if fails:
        warnings.warn(
            f"{len(fails)} pairs failed and are not in the store (first: {fails[0]}); rerun the same command to retry them",
            stacklevel=3,
        )
