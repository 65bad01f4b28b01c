"""Taichi start-up: one place that picks the backend and its limits."""

from __future__ import annotations

import logging
import os

import taichi as ti

log = logging.getLogger(__name__)
_ARCHS = {"cpu": ti.cpu, "cuda": ti.cuda}

# Every ti.init starts a new "generation": fields of an older one must never be touched again
# (taichi aborts the process), so each map remembers the generation it was built in.
_generation = 0
_map_owner: int | None = None  # generation that already holds a map


def generation() -> int:
    return _generation


def claim_map_slot() -> int:
    """Reserve this runtime for one map and return its generation.

    taichi 1.7.4's CPU allocator corrupts memory once its sparse node pools need a second
    1 GiB chunk (the end of its first chunk is computed past the mapping), and each map's sparse
    trees reserve several hundred MB of pool on creation that are never given back, even when
    the tree is destroyed. Two maps in one runtime therefore risk a heap corruption; one map per
    `init_taichi()` keeps every map in the first chunk. Refuse clearly instead of crashing.
    """
    global _map_owner
    ensure_initialized()
    if _map_owner == _generation:
        raise RuntimeError(
            "a tisem map already lives in this Taichi runtime; taichi 1.7.4 cannot hold two "
            "sparse maps safely. Call tisem.init_taichi() to start a fresh runtime (the old map "
            "becomes unusable), or run the second map in another process."
        )
    _map_owner = _generation
    return _generation


def is_initialized() -> bool:
    return ti.lang.impl.get_runtime().prog is not None


def available_cores() -> int:
    """CPU cores this process may run on (its affinity mask where the OS has one)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def usable_threads(requested: int) -> int:
    """The kernel threads to start for `requested`: ValueError below 1; above the cores
    available, the cores available (each Taichi CPU thread is an OS thread: 100,000 of them
    exhaust the machine's process limit), with one warning saying so."""
    if isinstance(requested, bool) or not isinstance(requested, int) or requested < 1:
        raise ValueError(
            f"--threads {requested}: expected a whole number >= 1 (the CPU threads of the kernels)"
        )
    cores = available_cores()
    if requested > cores:
        log.warning(
            "--threads %d: this machine has %d cores available; using %d threads",
            requested,
            cores,
            cores,
        )
        return cores
    return requested


def init_taichi(
    arch: str = "cpu", threads: int | None = 2, debug: bool = False, device_memory_gb: float = 4.0
) -> str:
    """Initialise Taichi on `arch` ("cpu" or "cuda"); returns the arch actually running.

    `threads`: CPU threads for the kernels (None: Taichi's default), refused below 1 and
    capped at the cores available (`usable_threads`). Sparse SNodes exist only on CPU and
    CUDA in taichi 1.7.4, so other backends are refused rather than silently falling back.
    CUDA sparse memory comes from a preallocated pool (1 GB by default), so its size is set
    explicitly.
    """
    if arch not in _ARCHS:
        raise ValueError(f"arch must be one of {sorted(_ARCHS)}, got {arch!r}")
    kwargs = dict(arch=_ARCHS[arch], debug=debug, log_level=ti.WARN, random_seed=0)
    if arch == "cpu" and threads is not None:
        kwargs["cpu_max_num_threads"] = usable_threads(threads)
    if arch == "cuda":
        kwargs["device_memory_GB"] = float(device_memory_gb)
    global _generation
    ti.init(**kwargs)
    _generation += 1
    running = ti.lang.impl.current_cfg().arch.name
    if running != _ARCHS[arch].name:
        raise RuntimeError(
            f"asked for --arch {arch} but Taichi started on {running} (no {arch} device available?)"
        )
    return running


def ensure_initialized() -> None:
    global _generation
    if not is_initialized():
        init_taichi("cpu", threads=None)
    elif _generation == 0:  # initialised by the user with ti.init directly
        _generation = 1


def on_cpu() -> bool:
    """Whether the running Taichi backend is a CPU (x64 or arm64)."""
    return ti.lang.impl.current_cfg().arch in (ti.x64, ti.arm64)


def describe() -> str:
    """A one-line description of the running backend, for logs and benchmark tables."""
    import platform

    cfg = ti.lang.impl.current_cfg()
    arch = cfg.arch.name
    if arch == "x64" or arch == "arm64":
        cpu = platform.processor() or platform.machine()
        return f"{arch} CPU ({cpu}), {cfg.cpu_max_num_threads} threads"
    return arch
