"""Shared pieces of the benchmarks: where the data is, how scans are replayed, the process's
memory, the device line."""

from __future__ import annotations

import argparse
import json
import platform
import resource
from pathlib import Path

import numpy as np

from tisem.scan import Scan

KITTI_MINI = Path(__file__).resolve().parents[2] / "shared" / "data" / "semantickitti_08_mini"
GIB = 1 << 30


def add_data_args(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--data",
        type=Path,
        default=None,
        help="SemanticKITTI sequence folder (default: "
        "../shared/data/semantickitti_08_mini when present, else a synthetic "
        "street)",
    )
    p.add_argument("--synthetic", action="store_true", help="use a synthetic street instead")
    p.add_argument("--arch", choices=("cpu", "cuda"), default="cpu")
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path, help="write the results as JSON here")


def load_scans(args, count: int) -> tuple[list[Scan], str]:
    """Up to `count` distinct scans from --data, the mini KITTI data, or a synthetic street."""
    from tisem.io.semantickitti import SemanticKittiSequence

    data = args.data
    if data is None and not args.synthetic and KITTI_MINI.is_dir():
        data = KITTI_MINI
    if data is not None:
        seq = SemanticKittiSequence(data, last=None)
        scans = [s for s in seq if isinstance(s, Scan)][:count]
        return scans, f"{data} ({len(scans)} scans)"
    from tisem.synth.sequence import iter_synthetic, to_scan

    scans = [to_scan(f) for f in iter_synthetic(count, seed=0)]
    return scans, f"synthetic street ({len(scans)} scans)"


def replay(scans: list[Scan], n: int, period_s: float = 0.1):
    """n scans cycling through `scans`, timestamps continuing at `period_s` so time moves on.

    With few distinct scans this is the steady state of a sensor circling one place: the map
    is revisited, not grown, which is what a sensor at 10 Hz sees from one scan to the next.
    """
    for k in range(n):
        s = scans[k % len(scans)]
        yield Scan(
            s.points_sensor,
            s.T_world_sensor,
            k * period_s,
            labels=s.labels,
            probs=s.probs,
            gt_labels=s.gt_labels,
            index=k,
            name=s.name,
        )


def peak_rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def rss_mb() -> float:
    import psutil

    return psutil.Process().memory_info().rss / 2**20


def vms_mb() -> float:
    import psutil

    return psutil.Process().memory_info().vms / 2**20


def gib_mappings() -> int:
    """Mappings of 1 GiB or more in this process (taichi's host chunks; Linux only)."""
    try:
        with open("/proc/self/maps") as f:
            spans = (line.split()[0].split("-") for line in f)
            return sum(1 for a, b in spans if int(b, 16) - int(a, 16) >= GIB)
    except OSError:
        return -1


def device_line(arch: str) -> str:
    from tisem.backend import describe

    return f"{describe()}, {platform.node()}, Python {platform.python_version()}"


def median(xs) -> float:
    return float(np.median(np.asarray(xs))) if len(xs) else float("nan")


def write_json(path, result: dict) -> None:
    """The benchmark's result as JSON (numpy scalars and paths as plain values)."""
    if path:
        path = Path(path)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(result, indent=2, default=_plain))


def _plain(x):
    return float(x) if isinstance(x, (np.floating, np.integer)) else str(x)


def benchmark_main(argv, parse_args, run, format_result) -> int:
    """Parse, run, print the result's table, write --json: every benchmark's `main`."""
    args = parse_args(argv)
    result = run(args)
    print(format_result(result))
    write_json(args.json, result)
    return 0
