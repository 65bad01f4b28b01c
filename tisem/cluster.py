"""The Ray side of fleets and batches: the cluster, tasks in their own processes, failures.

    with ray_cluster(address=None, num_cpus=None):      # a local cluster, or join one
        refs = {name: submit(map_task, cpus=2, retries=1, args=(...))}
        done, failed = gather(refs, "mapping")            # {name: result}, {name: reason}

Taichi holds one runtime per process and each tisem map needs its own runtime, so every task
runs in a fresh worker process (`max_calls=1`) and reserves as many CPUs as its kernels use
threads. A task that raises or whose process dies is retried as Ray allows (`retries`: worker
deaths always; exceptions only for OSError, which may be a passing file-system fault), then
reported with its reason, never raised: the rest goes on.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

from tisem.errors import RunError

log = logging.getLogger(__name__)

__all__ = ["ray_cluster", "submit", "gather", "cluster_cpus"]


@contextmanager
def ray_cluster(address: str | None = None, num_cpus: int | None = None) -> Iterator[None]:
    """Ray for the duration: an already initialised Ray is used as it is (and left running);
    otherwise `address` joins a cluster ("auto" or host:port) and None starts a local one on
    `num_cpus` cores (default: all), shut down at the end."""
    import ray

    if ray.is_initialized():
        yield
        return
    # worker processes import tisem the way this process does
    env = {"PYTHONPATH": os.environ["PYTHONPATH"]} if os.environ.get("PYTHONPATH") else {}
    kwargs: dict[str, Any] = {"log_to_driver": False, "runtime_env": {"env_vars": env}}
    try:
        if address:
            ray.init(address=address, **kwargs)
        else:
            _start_local(num_cpus, kwargs)
    except (ConnectionError, RuntimeError) as exc:
        where = f"join the Ray cluster at {address}" if address else "start a local Ray cluster"
        lines = str(exc).strip().splitlines()
        raise RunError(
            f"cannot {where}: {lines[-1] if lines else type(exc).__name__}"
            + (
                "; a cluster with token authentication needs its token (RAY_AUTH_TOKEN)"
                if "auth" in str(exc).lower()
                else ""
            )
        ) from None
    try:
        yield
    finally:
        ray.shutdown()


def _start_local(num_cpus: int | None, kwargs: dict) -> None:
    """ray.init of a local cluster. Ray gives its node 30 s to come up, which a loaded
    machine can miss: then once more, and a RuntimeError after that."""
    import ray

    for attempt in range(2):
        try:
            ray.init(num_cpus=num_cpus, include_dashboard=False, **kwargs)
            return
        except Exception as exc:  # noqa: BLE001 (Ray raises a bare Exception here)
            if "timed out during startup" not in str(exc):
                raise
            ray.shutdown()
            log.warning("the local Ray cluster did not start in time (attempt %d)", attempt + 1)
    raise RuntimeError(
        "the local Ray node did not start in 30 s, twice (is the machine overloaded?)"
    )


def cluster_cpus() -> int:
    import ray

    return int(ray.cluster_resources().get("CPU", 1))


def submit(
    fn: Callable, *, cpus: float = 1, retries: int = 1, args: tuple = (), kwargs: dict | None = None
):
    """`fn(*args, **kwargs)` as a Ray task in a process of its own; returns its ref."""
    import ray

    remote = ray.remote(
        num_cpus=cpus, max_calls=1, max_retries=int(retries), retry_exceptions=[OSError]
    )(fn)
    return remote.remote(*args, **(kwargs or {}))


def _reason(exc: BaseException) -> str:
    """The last line of a task's error (its exception), or the kind of failure."""
    import ray

    if isinstance(exc, ray.exceptions.RayTaskError):
        cause = exc.cause
        if cause is not None:
            return f"{type(cause).__name__}: {cause}".strip().splitlines()[0][:500]
    text = str(exc).strip().splitlines()
    return f"{type(exc).__name__}: {text[-1] if text else ''}"[:500]


def gather(refs: dict[str, Any], what: str | None = None) -> tuple[dict[str, Any], dict[str, str]]:
    """Wait for every task: ({name: result} of those that finished, {name: reason} of those
    that failed after their retries). With `what`, a progress bar of that name counts the
    tasks as they end (a fleet's tasks run for minutes each, and nothing else prints)."""
    import ray
    from tqdm import tqdm

    done, failed = {}, {}
    by_ref = {ref: name for name, ref in refs.items()}
    pending = list(by_ref)
    with tqdm(total=len(pending), desc=what, unit="task", disable=what is None) as bar:
        while pending:
            ready, pending = ray.wait(pending, num_returns=1)
            name = by_ref[ready[0]]
            try:
                done[name] = ray.get(ready[0])
            except (ray.exceptions.RayError, Exception) as exc:  # noqa: B902 (reported)
                failed[name] = _reason(exc)
                log.warning("task %s failed: %s", name, failed[name])
                bar.set_postfix(failed=len(failed))
            bar.update(1)
    return done, failed
