"""Taichi start-up: one place that picks the backend and its limits."""
from __future__ import annotations

import logging

import taichi as ti

log = logging.getLogger(__name__)
_ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda}


def is_initialized() -> bool:
    return ti.lang.impl.get_runtime().prog is not None


def init_taichi(arch: str = "cpu", threads: int | None = 2, debug: bool = False,
                device_memory_gb: float = 4.0) -> str:
    """Initialise Taichi on `arch` ("cpu" or "cuda"); returns the arch actually running.

    Sparse SNodes exist only on CPU and CUDA in taichi 1.7.4, so other backends are refused
    rather than silently falling back. CUDA sparse memory comes from a preallocated pool
    (1 GB by default), so its size is set explicitly.
    """
    if arch not in _ARCHS:
        raise ValueError(f"arch must be one of {sorted(_ARCHS)}, got {arch!r}")
    kwargs = dict(arch=_ARCHS[arch], debug=debug, log_level=ti.WARN, random_seed=0)
    if arch == "cpu" and threads:
        kwargs["cpu_max_num_threads"] = int(threads)
    if arch == "cuda":
        kwargs["device_memory_GB"] = float(device_memory_gb)
    ti.init(**kwargs)
    running = ti.lang.impl.current_cfg().arch.name
    if running != _ARCHS[arch].name:
        raise RuntimeError(f"asked for --arch {arch} but Taichi started on {running} "
                           f"(no {arch} device available?)")
    return running


def ensure_initialized() -> None:
    if not is_initialized():
        init_taichi("cpu", threads=None)


def describe() -> str:
    """A one-line description of the running backend, for logs and benchmark tables."""
    import platform
    cfg = ti.lang.impl.current_cfg()
    arch = cfg.arch.name
    if arch == "x64" or arch == "arm64":
        return f"{arch} CPU ({platform.processor() or platform.machine()}), {cfg.cpu_max_num_threads} threads"
    return arch
