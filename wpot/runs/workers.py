"""What a worker does: its device (`choose_worker_device`), its cached `Comparer` and meshes, the shape and pair
tasks it runs, and the Dask executor (`dask_executor`)."""
from __future__ import annotations

import concurrent.futures as cf
import contextlib
import functools
import json
import os
import socket
import time
import warnings
from typing import Any, Iterator, Mapping


from wpot.mesh import Mesh, repair_mesh, repair_mode

__all__ = ["DaskExecutor", "choose_worker_device", "dask_executor", "fit_input_of", "pair_task", "shape_task", "signatures_of"]

def _worker_rank(name: Any) -> int | None:
    """A worker's index from its Dask name: 3, "3" or "host-3" give 3; anything else None."""
    if isinstance(name, bool):
        return None
    if isinstance(name, int):
        return name if name >= 0 else None
    if isinstance(name, str):
        tail = name.rsplit("-", 1)[-1]
        if tail.isdigit():
            return int(tail)
    return None


def choose_worker_device(*, worker_name: Any, cuda_count: int, env: Mapping[str, str]) -> str | None:
    """The Warp device a Dask worker uses when the run names none (a pure function of the worker's view).

    Parameters
    ----------
    worker_name : the worker's Dask name (`LocalCluster`: 0, 1, ...; ``dask worker --name h --nworkers 2``:
        "h-0", "h-1"; otherwise often its address)
    cuda_count : CUDA devices the worker's process sees (Warp's ``get_cuda_device_count()``)
    env : the worker's environment

    Returns
    -------
    ``env["WPOT_DEVICE"]`` when set (an operator's explicit choice); ``"cpu"`` without CUDA; ``"cuda:0"``
    when ``CUDA_VISIBLE_DEVICES`` is set (the launcher chose this worker's GPUs and put its own first, as
    dask-cuda does); ``"cuda:<rank mod cuda_count>"`` when the name ends in a worker rank (several workers
    of one machine then spread over its GPUs); otherwise None: Warp's default device.
    """
    explicit = (env.get("WPOT_DEVICE") or "").strip()
    if explicit:
        return explicit
    if cuda_count < 0:
        raise ValueError(f"cuda_count must be >= 0, got {cuda_count!r}")
    if cuda_count == 0:
        return "cpu"
    if (env.get("CUDA_VISIBLE_DEVICES") or "").strip():
        return "cuda:0"
    rank = _worker_rank(worker_name)
    if rank is not None:
        return f"cuda:{rank % cuda_count}"
    return None


def _dask_worker_name() -> tuple[bool, Any]:
    """(True, name) inside a Dask worker, else (False, None). Never imports Dask when it is not loaded."""
    import sys

    if "distributed" not in sys.modules:
        return False, None
    try:
        from distributed import get_worker

        return True, get_worker().name
    except (ImportError, ValueError):  # ValueError: not running in a worker
        return False, None


def _task_device(config: Mapping[str, Any]) -> str | None:
    """The device of this task: the run's ``device``; when None, the Dask worker's own choice
    (`choose_worker_device`); elsewhere (inline, process pool) Warp's default."""
    if config.get("device") is not None:
        return config["device"]
    on_dask, name = _dask_worker_name()
    if not on_dask:
        return None
    import warp as wp

    from wpot._warp import resolve_device

    resolve_device(None)  # initializes Warp
    return choose_worker_device(worker_name=name, cuda_count=wp.get_cuda_device_count(), env=os.environ)


@functools.lru_cache(maxsize=1)
def _comparer_for(config_json: str):
    """The `Comparer` a worker rebuilds from a task's configuration (memoized: one per run and process)."""
    from wpot.comparison import Comparer
    from wpot.config import ComparisonConfig

    config = json.loads(config_json)
    return Comparer(ComparisonConfig.from_dict(config["config"]), signature_state=config.get("state"),
                    cache_dir=config.get("cache_dir"), device=_task_device(config))


def _worker_comparer(config: Mapping[str, Any]):
    return _comparer_for(json.dumps(config, sort_keys=True))


@functools.lru_cache(maxsize=64)
def _mesh_at(path: str, repair: str = "none") -> Mesh:
    from wpot.io import load_mesh

    # the coordinator said the mesh's defects once, when it read the shapes
    return repair_mesh(load_mesh(path, warn=False), repair)[0]


def _worker_mesh(spec: Any, config: Mapping[str, Any]) -> Mesh:
    """A task's mesh: given, or read from its path (and repaired when the run repairs its meshes).

    A path comes with the fingerprint the coordinator read (``(path, fingerprint)``): a file edited after the
    run began raises ValueError naming it (the pair is recorded in ``failures``), so a pair is never computed
    on another mesh than the one the run's shapes table describes."""
    if isinstance(spec, Mesh):
        return spec
    path, fingerprint = spec if isinstance(spec, tuple) else (spec, None)
    mesh = _mesh_at(path, repair_mode(config.get("repair", False)))
    if fingerprint is not None and mesh.fingerprint != fingerprint:
        _mesh_at.cache_clear()
        raise ValueError(f"{path} changed while the run was going (its content is not the one the run began "
                         "with); restore it, or start a new run folder")
    return mesh


#: what ``repair`` asks for (`repair_mode`): nothing; the defects `Mesh.validate` warns about (zero-area and
#: duplicate triangles, unreferenced vertices); or those and then every connected component but the largest
#: (scans with stray pieces, TOSCA's seahorses with their two detached eyes)


def shape_task(fn: Any, spec: Any, config: Mapping[str, Any]) -> tuple[Any, list[tuple[type, str]]]:
    """``fn(mesh, config)`` on one shape's mesh, with the warnings it raised returned beside its result rather
    than printed where it ran (a worker process prints them without saying which shape they are about):
    `_map` says each again, once, in the coordinator, prefixed with the shape's file name."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        value = fn(_worker_mesh(spec, config), config)
    said = [(w.category, str(w.message)) for w in caught]
    return value, list(dict.fromkeys(said))


def signatures_of(mesh: Mesh, config: Mapping[str, Any]) -> int:
    """Compute (and cache on disk) one shape's signatures; returns its vertex count."""
    _worker_comparer(config).signatures(mesh)
    return mesh.n_vertices


def fit_input_of(mesh: Mesh, config: Mapping[str, Any]) -> Any:
    """One shape's contribution to fitting the signature to the dataset (`Signature.fit_input`: for WKS, its
    eigenvalues; the eigenvectors stay in the run's spectrum cache, on disk)."""
    return _worker_comparer(config).stage.fit_input(mesh)


def pair_task(i: int, j: int, spec_i: Any, spec_j: Any, config: Mapping[str, Any]) -> dict[str, Any]:
    """Solve one pair (raw energy U and its per-β history), self-contained so any executor can run it."""
    t0 = time.perf_counter()
    comp = _worker_comparer(config)
    a = _worker_mesh(spec_i, config)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # non-convergence is recorded in the store's `converged` column
        if i == j:
            res = comp.self_transport(a)
        else:
            res = comp.transport_plan(a, _worker_mesh(spec_j, config))
    return {
        "i": i,
        "j": j,
        "energy": float(res.objective),
        "history": res.energy_history.tolist(),
        "converged": bool(res.converged),
        "n_newton": int(res.n_newton),
        "n_linear": int(res.n_linear),
        "seconds": time.perf_counter() - t0,
        "worker": f"{socket.gethostname()}:{os.getpid()}@{comp.device}",
    }


# ------------------------------------------------------------------------------------------------ runner


class DaskExecutor(cf.Executor):
    """A `concurrent.futures.Executor` on a Dask ``distributed.Client`` that `run_all_vs_all` keeps busy
    without over-committing: it holds at most one task per worker thread in flight (`max_in_flight`).

    Each worker then holds only the pair it is computing: when a worker dies, Dask blames (counts towards
    ``allowed-failures``) only that pair, not pairs queued behind it, and the loss is that one pair. Tasks
    are impure (``pure=False``): every submission runs. A plain ``client.get_executor()`` also works
    with `run_all_vs_all`, but then every pair is submitted at once.
    """

    #: what `run_all_vs_all` says about the pairs in flight when a signal stops it (`dask_executor` sets it for
    #: a local cluster, whose workers it stops)
    stop_words = "the pairs in flight were cancelled on the Dask cluster and dropped"

    def __init__(self, client: Any) -> None:
        self.client = client
        self._inner = client.get_executor(pure=False)

    def submit(self, fn: Any, /, *args: Any, **kwargs: Any) -> cf.Future:
        return self._inner.submit(fn, *args, **kwargs)

    def max_in_flight(self) -> int:
        """Worker threads of the cluster now (at least 1, so that a run waits for workers to come back)."""
        return max(1, int(sum(self.client.nthreads().values())))

    def shutdown(self, wait: bool = True, *, cancel_futures: bool = False) -> None:
        self._inner.shutdown(wait=wait and not cancel_futures)


@contextlib.contextmanager
def dask_executor(scheduler: Any, *, n_workers: int | None = None, connect_timeout: float = 30.0) -> Iterator[DaskExecutor]:
    """A `DaskExecutor` for `run_all_vs_all` (a context manager).

    Parameters
    ----------
    scheduler : ``"local"``: start an embedded `distributed.LocalCluster` of ``n_workers`` worker processes
        (one thread each; None: one per CPU core), closed on exit. ``"tcp://host:port"`` (or another Dask
        address such as ``tls://``): connect to that running scheduler; its workers are used as they are.
        A ``distributed.Client``: use it (it is left open).
    n_workers : workers of the local cluster (ignored otherwise)
    connect_timeout : seconds to wait for a remote scheduler

    Raises
    ------
    ImportError : Dask's ``distributed`` is not installed (names the extra: ``pip install 'wpot[cluster]'``)
    ValueError : ``scheduler`` is neither "local" nor an address nor a client, or ``n_workers < 1``
    OSError : the scheduler cannot be reached
    """
    is_client = type(scheduler).__name__ == "Client" and hasattr(scheduler, "get_executor")
    if not is_client and not (isinstance(scheduler, str) and (scheduler == "local" or "://" in scheduler)):
        raise ValueError(f'scheduler must be "local", a Dask address like "tcp://host:8786" or a Client, got {scheduler!r}')
    if n_workers is not None and n_workers < 1:
        raise ValueError(f"n_workers must be >= 1 or None, got {n_workers!r}")
    try:
        import dask  # noqa: F401  (checked here so that the message below names what is missing)
        from distributed import Client, LocalCluster
    except ImportError as exc:
        raise ImportError(
            f"running on a Dask cluster (scheduler={scheduler!r}) needs Dask's distributed package: "
            "pip install 'wpot[cluster]' (or 'dask[distributed]')"
        ) from exc
    cluster = executor = None
    started: set = set()  # the clusters that this call started (a start that a signal broke leaves one behind)
    with contextlib.ExitStack() as stack:
        try:
            if is_client:
                client = scheduler
            elif scheduler == "local":
                from distributed.deploy.spec import SpecCluster

                from wpot.stopping import deferred_stop

                started = set(SpecCluster._instances)
                with deferred_stop():  # a signal stops the run once the cluster is up (and in the stack, to close)
                    cluster = stack.enter_context(
                        LocalCluster(
                            n_workers=n_workers or os.cpu_count() or 1, threads_per_worker=1, processes=True,
                            dashboard_address="127.0.0.1:0",  # a free port (8787 may be taken)
                            preload=["wpot.stopping"],  # its dask_setup: the workers ignore SIGINT and SIGTERM
                        )
                    )
                    client = stack.enter_context(Client(cluster))
            else:
                client = stack.enter_context(Client(scheduler, timeout=connect_timeout))
            executor = DaskExecutor(client)
            if cluster is not None:
                executor.stop_words = "the local Dask cluster's workers were stopped and the pairs they were computing dropped"
            yield executor
        except KeyboardInterrupt:  # a signal stopped the run: its pairs in flight are dropped
            if executor is not None:
                executor.shutdown(wait=False, cancel_futures=True)
            if cluster is not None:
                with _quiet_dask():
                    _stop_local_workers(cluster)
                    stack.close()  # the client, then the cluster
            elif scheduler == "local":
                with _quiet_dask():
                    _abandon_broken_clusters(started)
            raise
        finally:
            if executor is not None:
                executor.shutdown(wait=False, cancel_futures=True)


@contextlib.contextmanager
def _quiet_dask() -> Iterator[None]:
    """Dask's warnings about workers it kills, and about tasks cancelled, kept quiet for the block."""
    import logging

    loggers = [logging.getLogger(n) for n in ("distributed", "tornado")]
    levels = [lg.level for lg in loggers]
    for lg in loggers:
        lg.setLevel(logging.CRITICAL)
    try:
        yield
    finally:
        for lg, level in zip(loggers, levels):
            lg.setLevel(level)


def _abandon_broken_clusters(before: set) -> None:
    """The `LocalCluster` whose start a signal broke (the clusters not in ``before``): its workers closed now, and
    Dask's exit handler told to leave it (it would wait up to 10 s on a cluster that never started)."""
    from distributed.deploy.spec import SpecCluster

    for cluster in set(SpecCluster._instances) - before:
        _stop_local_workers(cluster)
        cluster.shutdown_on_close = False


def _stop_local_workers(cluster: Any, timeout: float = 0.5) -> None:
    """Close a `LocalCluster`'s workers now (a signal stopped the run): each nanny asks its worker to stop and
    kills it after ``timeout`` seconds, rather than after the 4 s Dask's close allows a worker busy with a pair."""
    import asyncio

    async def close_all() -> None:
        await asyncio.gather(*(w.close(timeout=timeout, reason="wpot-interrupted") for w in list(cluster.workers.values())),
                             return_exceptions=True)

    with contextlib.suppress(Exception):  # the cluster is closed next in any case (its processes end with this one)
        cluster.sync(close_all)
