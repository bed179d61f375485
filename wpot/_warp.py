"""Warp start-up and device resolution, in one place for every wpot module that launches kernels.

Warp's native library prints "Warp CUDA warning: Could not find or load the NVIDIA CUDA driver" to the
process's standard error (file descriptor 2, below Python's ``sys.stderr``) whenever it starts on a
machine without a GPU, which is the normal case for CPU runs and says nothing the user can act on.
`init` starts Warp with descriptor 2 captured, drops that one line and writes everything else back, so
any other start-up message still reaches the user. `resolve_device` refuses a CUDA device on a machine
without one before Warp is asked for it, because asking prints raw CUDA driver errors.
"""
from __future__ import annotations

import os
import sys
import tempfile
import threading

import warp as wp

# Warp >= 1.19 reads log_level (not the older config.quiet) for its start-up greeting.
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)

#: start-up lines of Warp's native library that `init` drops (all others are passed through)
BENIGN_STARTUP_LINES = ("Warp CUDA warning: Could not find or load the NVIDIA CUDA driver",)

_lock = threading.Lock()
_initialized = False


def _filter_startup_output(data: bytes) -> bytes:
    """``data`` without the lines that start with one of `BENIGN_STARTUP_LINES`."""
    kept = [
        line
        for line in data.splitlines(keepends=True)
        if not line.decode("utf-8", "replace").startswith(BENIGN_STARTUP_LINES)
    ]
    return b"".join(kept)


def init() -> None:
    """Initialize Warp once, without its "no CUDA driver" start-up warning.

    Everything else Warp's native code writes to standard error while starting is written back
    unchanged, and an exception from ``wp.init()`` propagates. Where descriptor 2 cannot be captured
    (no such descriptor, or no temporary file), Warp starts as it would without wpot.
    """
    global _initialized
    if _initialized:
        return
    with _lock:
        if _initialized:
            return
        try:
            saved = os.dup(2)
        except OSError:
            wp.init()
            _initialized = True
            return
        try:
            capture = tempfile.TemporaryFile()
        except OSError:
            os.close(saved)
            wp.init()
            _initialized = True
            return
        with capture:
            for stream in (sys.stdout, sys.stderr):
                try:
                    stream.flush()
                except (AttributeError, OSError, ValueError):
                    pass
            os.dup2(capture.fileno(), 2)
            try:
                wp.init()
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                capture.seek(0)
                rest = _filter_startup_output(capture.read())
                if rest:
                    os.write(2, rest)
        _initialized = True


def resolve_device(device: str | wp.context.Device | None = None) -> wp.context.Device:
    """The Warp device for ``device``: None means Warp's default device (``"cuda:0"`` when a GPU is
    present, else ``"cpu"``). Initializes Warp on first use (see `init`).

    Raises
    ------
    ValueError : the name is not a device Warp knows, or names a CUDA device on a machine without one;
        the message gives the received value and the devices that exist.
    """
    init()
    if isinstance(device, str) and device.split(":", 1)[0] == "cuda" and wp.get_cuda_device_count() == 0:
        # Checked here: Warp's own lookup of "cuda" calls the missing driver and prints raw errors first.
        raise ValueError(
            f"device {device!r} needs a CUDA GPU, and none is available on this machine "
            f"(no NVIDIA driver or no GPU found); available devices: {[str(d) for d in wp.get_devices()]}"
        )
    try:
        return wp.get_device(device)
    except Exception as exc:  # Warp raises RuntimeError/ValueError for unknown names
        known = [str(d) for d in wp.get_devices()]
        raise ValueError(f"unknown Warp device {device!r} (available: {known}): {exc}") from None


def host_available_bytes() -> float:
    """MemAvailable of /proc/meminfo (Linux); elsewhere the free physical pages; inf when unknown."""
    import math

    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return float(line.split()[1]) * 1024.0
    except OSError:
        pass
    try:
        return float(os.sysconf("SC_AVPHYS_PAGES")) * float(os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return math.inf


def available_memory(device: str | wp.context.Device, *, host_too: bool = False) -> float:
    """Bytes an allocation on ``device`` can use now: the host's available memory for "cpu" (read from the
    operating system, not from Warp, whose CPU figure needs psutil), the GPU's free memory for CUDA, and for
    CUDA with ``host_too`` the smaller of the two (a result copied back to the host needs both)."""
    dev = resolve_device(device)
    if not dev.is_cuda:
        return host_available_bytes()
    free = float(dev.free_memory)
    return min(free, host_available_bytes()) if host_too else free


def cpu_threads() -> int:
    """The cores this process may run on: its CPU affinity where the OS reports one, else ``os.cpu_count()``."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):
        return max(1, os.cpu_count() or 1)


#: entries (rows x columns) per host thread below which `launch_rows` does not split a CPU launch (starting a
#: thread costs more than a pass over fewer entries; the docs' Results page has the figures)
MIN_ENTRIES_PER_THREAD = 2**16


def launch_rows(launch, n: int, device, *, cols: int = 1, threads: int | None = None) -> None:
    """Run ``launch(lo, hi)``, a kernel launch over rows ``lo .. hi - 1`` that reads anything and writes only
    those rows' outputs (no atomic sums across rows: Warp's CPU atomics are plain additions), over rows
    ``0 .. n - 1``.

    On a GPU it is one launch. On the CPU, Warp runs a launch on one thread without SIMD (NVIDIA/warp issue
    1309) and releases the GIL while it runs, so the rows are cut into ``threads`` contiguous chunks (default:
    `cpu_threads`; at least `MIN_ENTRIES_PER_THREAD` entries each, a row being ``cols`` entries) launched from as
    many host threads at once. Each row is computed by the same code whatever the cut, so the results are the
    same bit for bit."""
    n = int(n)
    if n <= 0:
        return
    t = cpu_threads() if threads is None else int(threads)
    t = max(1, min(t, n, n * max(1, int(cols)) // MIN_ENTRIES_PER_THREAD))
    if t == 1 or not resolve_device(device).is_cpu:
        launch(0, n)
        return
    from concurrent.futures import ThreadPoolExecutor

    bounds = [n * i // t for i in range(t + 1)]
    with ThreadPoolExecutor(max_workers=t) as pool:
        jobs = [pool.submit(launch, lo, hi) for lo, hi in zip(bounds[:-1], bounds[1:])]
        for j in jobs:
            j.result()  # re-raises a chunk's exception
