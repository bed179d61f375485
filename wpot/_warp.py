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
