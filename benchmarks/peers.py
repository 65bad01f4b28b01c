"""tisem against S-BKI (C++, upstream and tuned settings) on the same scans, in one run.

    python benchmarks/peers.py                          # mini KITTI: frames 0-4, 0-2, 3-4
    python benchmarks/peers.py --splits 0-2 3-4 --rounds 3 --json peers.json
    python benchmarks/peers.py --methods st adaptive bki6 sbki-tuned --set thin_classes=[]
    python benchmarks/peers.py --data /tmp/calib60 --splits 0-59 --rounds 1

Every split (an inclusive frame range) is mapped alone and scored on its own frames (final-map
protocol), so a split held out from a parameter choice is scored without the frames the choice
was made on (docs/method.md). The methods take turns within each round (tisem's modes through
`tisem.pipeline.run_pipeline`, each in a fresh Taichi runtime; S-BKI as its own process), so a
drift in the machine's speed hits them alike. Seconds per scan: medians over the rounds of each
run's median per scan (tisem: after the first scan, which compiles the kernels; S-BKI: its
driver's median `insert_pointcloud` time). Accuracy, mIoU and per-class IoU come from the last
round (both mappers are deterministic on a CPU).

S-BKI runs when its driver is built (`../shared/peers/sbki/build.sh` builds it where
`--sbki-bin` points by default); else its rows are skipped with a message. Methods: st,
adaptive, spatial, csm, bkiN (the fixed kernel of N voxels: bki4 is 0.8 m at 0.2 m voxels),
sbki-upstream, sbki-tuned.
"""

from __future__ import annotations

import argparse
import logging
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import KITTI_MINI, benchmark_main, device_line, median

log = logging.getLogger("peers")

TISEM_METHODS = ("st", "adaptive", "spatial", "csm")
SBKI_METHODS = {"sbki-upstream": [], "sbki-tuned": ["--tuned"]}
DEFAULT_METHODS = ("st", "adaptive", "bki6", "bki4", "csm", "sbki-upstream", "sbki-tuned")
SBKI_BIN = Path(tempfile.gettempdir()) / "sbki-build" / "build" / "sbki_kitti"
METRICS = ("miou", "accuracy", "wiou", "per_class_iou", "present_classes", "points")


def parse_args(argv=None):
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument("--data", type=Path, default=None, help="sequence folder (default: mini KITTI)")
    p.add_argument(
        "--splits",
        nargs="+",
        default=["0-4", "0-2", "3-4"],
        help="inclusive frame ranges FIRST-LAST, each mapped and scored alone",
    )
    p.add_argument("--methods", nargs="+", default=list(DEFAULT_METHODS))
    p.add_argument("--rounds", type=int, default=2, help="rounds in which every method runs once")
    p.add_argument("--config", type=Path, help="tisem config YAML (default: tisem's defaults)")
    p.add_argument(
        "--set",
        dest="overrides",
        action="append",
        default=[],
        metavar="KEY=VALUE",
        help="tisem config override (every tisem method)",
    )
    p.add_argument("--sbki-bin", type=Path, default=SBKI_BIN, help="the built S-BKI driver")
    p.add_argument("--out", type=Path, default=Path("results/peers"))
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", type=Path)
    args = p.parse_args(argv)
    for m in args.methods:
        if not (m in TISEM_METHODS or m in SBKI_METHODS or re.fullmatch(r"bki\d+(\.\d+)?", m)):
            p.error(
                f"unknown method {m!r}: one of {', '.join(TISEM_METHODS)}, bkiN, "
                f"{', '.join(SBKI_METHODS)}"
            )
    for s in args.splits:
        if not re.fullmatch(r"\d+(-\d+)?", s):
            p.error(f"--splits {s}: expected FIRST-LAST (inclusive frame numbers)")
    if args.data is None and not KITTI_MINI.is_dir():
        p.error(f"no --data and the mini KITTI data is not at {KITTI_MINI}")
    return args


def parse_split(text: str) -> tuple[int, int]:
    first, _, last = text.partition("-")
    return int(first), int(last or first)


def tisem_overrides(method: str) -> list[str]:
    if method.startswith("bki"):
        return ["mode=bki", f"ell_fixed_vox={method[3:]}"]
    return [f"mode={method}"]


def run_tisem(args, data: Path, split: tuple[int, int], method: str, out: Path) -> dict:
    from tisem.backend import init_taichi
    from tisem.config import load_config
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.pipeline import run_pipeline

    cfg = load_config(args.config, [*args.overrides, *tisem_overrides(method)])
    cfg.online_eval = False
    seq = SemanticKittiSequence(data, first=split[0], last=split[1])
    init_taichi("cpu", threads=args.threads)
    result = run_pipeline(
        seq,
        cfg,
        out,
        sequence_name=seq.sequence_name,
        total=len(seq),
        progress=False,
        write_outputs=False,
        source_info={"data": str(data)},
    )
    seconds = result.progress.seconds
    # the first scan compiles the kernels: the steady state is the median after it
    steady = median(seconds[1:]) if len(seconds) > 1 else median(seconds)
    return {
        "final": result.metrics["final"],
        "input": result.metrics["input"],
        "seconds_per_scan": steady,
        "dropped": result.metrics["dropped"],
    }


def score_predictions(data: Path, split: tuple[int, int], pred_dir: Path) -> dict:
    """Final-map metrics of SemanticKITTI prediction files (raw ids) against the ground truth,
    scored like tisem's own (non-finite points are not scored)."""
    from tisem.evaluate import Confusion
    from tisem.io.semantickitti import SemanticKittiSequence
    from tisem.labels import raw_to_train
    from tisem.scan import Scan, finite_rows

    conf = Confusion()
    for scan in SemanticKittiSequence(data, first=split[0], last=split[1]):
        if not isinstance(scan, Scan) or scan.gt_labels is None:
            continue
        path = pred_dir / f"{scan.index:06d}.label"
        pred, _ = raw_to_train(np.fromfile(path, dtype="<u4"))
        if len(pred) != scan.num_points:
            raise RuntimeError(f"{path}: {len(pred)} predictions for {scan.num_points} points")
        ok = finite_rows(scan.points_sensor)
        conf.add(scan.gt_labels[ok], pred[ok])
    return conf.metrics()


def run_sbki(args, data: Path, split: tuple[int, int], method: str, out: Path) -> dict:
    # the driver names its sequence folder after the data folder: predictions an earlier run
    # on other data left in `out` would otherwise be scored in place of this run's
    shutil.rmtree(out / "sequences", ignore_errors=True)
    out.mkdir(parents=True, exist_ok=True)
    cmd = [
        str(args.sbki_bin),
        "--data",
        str(data),
        "--out",
        str(out),
        "--first",
        str(split[0]),
        "--last",
        str(split[1]),
        *SBKI_METHODS[method],
    ]
    env = dict(os.environ, OMP_NUM_THREADS=str(args.threads))
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    (out / "sbki.log").write_text(proc.stdout + proc.stderr)
    found = re.findall(r"^sbki_s_per_scan=([0-9.eE+-]+)", proc.stdout, re.M)
    if proc.returncode != 0 or not found:
        raise RuntimeError(f"{' '.join(cmd)} failed ({proc.returncode}): {proc.stderr[-500:]}")
    pred_dir = next(out.glob("sequences/*/predictions"))
    return {"final": score_predictions(data, split, pred_dir), "seconds_per_scan": float(found[-1])}


def unbuilt_peer(args, methods: list[str]) -> dict[str, str]:
    """{S-BKI method: why it is skipped} when its driver is not built."""
    if args.sbki_bin.is_file():
        return {}
    reason = (
        f"S-BKI is not built ({args.sbki_bin} missing): run "
        f"../shared/peers/sbki/build.sh, or pass --sbki-bin"
    )
    return {m: reason for m in methods if m in SBKI_METHODS}


def run(args) -> dict:
    from tisem.backend import init_taichi

    data = args.data or KITTI_MINI
    init_taichi("cpu", threads=args.threads)  # (the device line asks it; tisem's runs renew it)
    splits = [parse_split(s) for s in args.splits]
    skipped = unbuilt_peer(args, args.methods)
    if skipped:
        log.warning("%s; its rows are skipped", next(iter(skipped.values())))
    methods = [m for m in args.methods if m not in skipped]
    runs: dict[tuple, dict] = {}
    times: dict[tuple, list] = {}
    for rnd in range(args.rounds):
        for split in splits:
            for method in methods:
                key = (f"{split[0]}-{split[1]}", method)
                t0 = time.perf_counter()
                runner = run_sbki if method in SBKI_METHODS else run_tisem
                r = runner(args, data, split, method, args.out / key[0] / method)
                runs[key] = r
                times.setdefault(key, []).append(r["seconds_per_scan"])
                log.info(
                    "round %d/%d, frames %s, %-13s mIoU %.4f accuracy %.4f  %.3f s/scan "
                    "(%.0f s wall)",
                    rnd + 1,
                    args.rounds,
                    key[0],
                    method,
                    r["final"]["miou"],
                    r["final"]["accuracy"],
                    r["seconds_per_scan"],
                    time.perf_counter() - t0,
                )
    rows = []
    for split in splits:
        name = f"{split[0]}-{split[1]}"
        inputs = [runs[(name, m)]["input"] for m in methods if "input" in runs[(name, m)]]
        if inputs:
            rows.append(
                {
                    "split": name,
                    "method": "network input",
                    **_metrics(inputs[0]),
                    "seconds_per_scan": None,
                }
            )
        for m in methods:
            r = runs[(name, m)]
            rows.append(
                {
                    "split": name,
                    "method": m,
                    **_metrics(r["final"]),
                    "seconds_per_scan": median(times[(name, m)]),
                    "seconds_all_rounds": times[(name, m)],
                    "dropped": r.get("dropped"),
                }
            )
    return {
        "data": str(data),
        "device": device_line("cpu"),
        "threads": args.threads,
        "rounds": args.rounds,
        "config": str(args.config) if args.config else None,
        "overrides": args.overrides,
        "rows": rows,
        "skipped": skipped,
    }


def _metrics(m: dict) -> dict:
    return {k: m[k] for k in METRICS}


def format_result(r: dict) -> str:
    from tisem.evaluate import format_per_class

    lines = [f"\ndata: {r['data']}", f"device: {r['device']}, {r['rounds']} rounds"]
    if r["config"] or r["overrides"]:
        lines.append(f"tisem settings: {r['config'] or 'defaults'} {' '.join(r['overrides'])}")
    for method, reason in r["skipped"].items():
        lines.append(f"skipped {method}: {reason}")
    lines += [
        "",
        "| frames | method | mIoU | accuracy | s / scan | st faster by |",
        "| --- | --- | ---: | ---: | ---: | ---: |",
    ]
    for row in r["rows"]:
        st = next(
            (x for x in r["rows"] if x["split"] == row["split"] and x["method"] == "st"), None
        )
        sps = row["seconds_per_scan"]
        ratio = (
            "–"
            if sps is None or st is None or not st["seconds_per_scan"]
            else f"{sps / st['seconds_per_scan']:.1f}x"
        )
        shown = "–" if sps is None else f"{sps:.3f}"
        lines.append(
            f"| {row['split']} | {row['method']} | {row['miou']:.4f} | "
            f"{row['accuracy']:.4f} | {shown} | {ratio} |"
        )
    for split in dict.fromkeys(x["split"] for x in r["rows"]):
        lines += ["", f"per-class IoU, frames {split}:", ""]
        lines.append(format_per_class([(x["method"], x) for x in r["rows"] if x["split"] == split]))
    return "\n".join(lines)


def main(argv=None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
