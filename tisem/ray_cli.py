"""The options the Ray apps (fleet, batch) share: the config, the cluster, each task's share."""

from __future__ import annotations

import argparse
from pathlib import Path

from tisem.config import MODES

__all__ = ["add_cluster_args", "add_config_args", "results_folder"]


def add_cluster_args(p: argparse.ArgumentParser) -> None:
    """The options of every Ray app: where the cluster is, and each task's share of it."""
    g = p.add_argument_group("cluster")
    g.add_argument(
        "--address", help="join this Ray cluster ('auto' or host:port); default: start a local one"
    )
    g.add_argument("--num-cpus", type=int, help="CPUs of the local cluster (default: all)")
    g.add_argument(
        "--threads", type=int, default=None, help="kernel threads per task, reserved as its CPUs"
    )
    g.add_argument("--retries", type=int, default=1, help="retries of a failed task")
    g.add_argument(
        "--arch", choices=("cpu", "cuda"), default="cpu", help="Taichi backend of the tasks"
    )
    g.add_argument(
        "--no-progress", action="store_true", help="no bars counting the tasks as they end"
    )


def add_config_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--mode", choices=MODES, help="method (default st)")
    p.add_argument("--config", type=Path, help="YAML config")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="override a config value (repeatable)",
    )
    p.add_argument("--sequences", nargs="+", help="sequences of a dataset root (default all)")
    p.add_argument("--out", type=Path, help="output folder (default results/<timestamp>/)")
    p.add_argument("-v", "--verbose", action="store_true", help="also tisem's debug lines")


def results_folder(out: Path | None) -> Path:
    """--out as given (a fleet or batch folder is reused on purpose: finished work in it is
    kept), else a new results/<timestamp>/."""
    from tisem.results_dir import RESULTS_ROOT, new_timestamped_dir

    return Path(out) if out is not None else new_timestamped_dir(Path(RESULTS_ROOT))
