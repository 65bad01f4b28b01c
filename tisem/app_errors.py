"""The errors of the command-line apps, and the one way input errors become them.

`AppError` is a bad command line or input (the app logs its one line and exits with status
2), `BackendError` a Taichi backend that cannot start. They live apart from `tisem.cli` so that
the pieces of an app's prologue (`tisem.results_dir`) can raise them without importing the
prologue itself; the apps use them as `cli.AppError` and `cli.bad_input`.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


class AppError(Exception):
    """A bad command line or input: the app logs this one line and exits with status 2."""


class BackendError(RuntimeError):
    """The requested Taichi backend cannot start (e.g. --arch cuda without a GPU)."""


@contextmanager
def bad_input(prefix: str = "") -> Iterator[None]:
    """Inside: the errors that mean 'this input cannot be used' (a config key, a value, a
    file, a `DatasetError`) become an `AppError` with their message (after `prefix`)."""
    try:
        yield
    except (KeyError, ValueError, OSError) as exc:
        message = exc.args[0] if isinstance(exc, KeyError) and exc.args else exc
        raise AppError(f"{prefix}{message}") from None
