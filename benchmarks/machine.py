"""The machine a benchmark ran on, for its results file (timings mean nothing without it)."""

from __future__ import annotations

import os
import platform

import jax


def describe() -> dict:
    """Platform, processor, CPU count, JAX version and the default device, as JSON-ready values."""
    device = jax.devices()[0]
    return {
        "platform": platform.platform(),
        "processor": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "device": str(device),
        "device_kind": device.device_kind,
    }
