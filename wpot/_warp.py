"""Warp start-up and device resolution, in one place for every wpot module that launches kernels."""
from __future__ import annotations

import warp as wp

# Warp >= 1.19 reads log_level (not the older config.quiet) for its start-up greeting.
wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)


def resolve_device(device: str | wp.context.Device | None = None) -> wp.context.Device:
    """The Warp device for ``device``: None means Warp's default device (``"cuda:0"`` when a GPU is
    present, else ``"cpu"``). Initializes Warp on first use.

    Raises
    ------
    ValueError : the name is not a device Warp knows, with the received value and the known devices.
    """
    wp.init()
    try:
        return wp.get_device(device)
    except Exception as exc:  # Warp raises RuntimeError/ValueError for unknown names
        known = [str(d) for d in wp.get_devices()]
        raise ValueError(f"unknown Warp device {device!r} (available: {known}): {exc}") from None
