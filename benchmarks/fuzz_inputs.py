"""A longer fuzz campaign: seeded damaged MCAP recordings, ROS 1 bags and SemanticKITTI folders
through the readers, each case judged by one oracle (`tisem.testing.oracle`).

    python benchmarks/fuzz_inputs.py --minutes 10                  # every target, a third each
    python benchmarks/fuzz_inputs.py --minutes 5 --target rosbag   # (needs rosbags: tisem[mcap])
    python benchmarks/fuzz_inputs.py --minutes 5 --target mcap --seed 3
    python benchmarks/fuzz_inputs.py --cases 500 --target kitti --json results/fuzz.json
    python benchmarks/fuzz_inputs.py --target mcap --seed 3 --case 86 --keep /tmp/case86

Outcomes: identical (every scan byte-identical to the intact input's), reported (scans skipped
with a reason or marked suspect, the rest identical), refused (the whole input, with the
project's error), undetectable (a valid value changed into another valid one), failure (a
signal, another exception, memory beyond the limit, a hang, or damage nothing reports). Every
failure is printed with its seed and case; `--case K --keep DIR` replays one case in this
process and keeps the damaged input.
"""

from __future__ import annotations

import argparse
import datetime as dt
import importlib.util
import sys
from pathlib import Path

if not __package__:  # run as `python benchmarks/NAME.py`: import from the checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from benchmarks.common import benchmark_main


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    p.add_argument(
        "--minutes",
        type=float,
        default=1.0,
        help="how long the campaign runs, all targets together (default 1)",
    )
    p.add_argument("--cases", type=int, help="run this many cases per target instead")
    p.add_argument("--seed", type=int, default=0, help="the campaign's seed (default 0)")
    p.add_argument("--target", choices=("mcap", "kitti", "rosbag", "all"), default="all")
    p.add_argument("--case", type=int, help="replay this one case (with --keep)")
    p.add_argument("--keep", type=Path, help="the folder a replayed case's input is kept in")
    p.add_argument("--json", type=Path, help="also write the results here")
    args = p.parse_args(argv)
    if args.minutes <= 0 or (args.cases is not None and args.cases < 1):
        p.error("--minutes must be > 0 and --cases >= 1")
    if args.case is not None and (args.keep is None or args.target == "all"):
        p.error("--case needs --keep DIR and one --target")
    return args


def run(args: argparse.Namespace) -> dict:
    from tisem.testing.fuzz import TARGETS, replay, run_campaign

    targets = TARGETS if args.target == "all" else (args.target,)
    if args.target == "all" and importlib.util.find_spec("rosbags") is None:
        print("rosbag target skipped: the rosbags package (tisem[mcap]) is not installed")
        targets = tuple(t for t in targets if t != "rosbag")
    if args.case is not None:
        args.keep.mkdir(parents=True, exist_ok=True)
        what, path, outcome = replay(args.target, args.seed, args.case, args.keep)
        return {
            "replay": {
                "target": args.target,
                "seed": args.seed,
                "case": args.case,
                "what": what,
                "input": str(path),
                "outcome": outcome.kind,
                "detail": outcome.detail,
            }
        }
    results = []
    for target in targets:
        minutes = None if args.cases else args.minutes / len(targets)
        results += run_campaign(target, args.seed, count=args.cases, minutes=minutes)
    return {
        "date": dt.date.today().isoformat(),
        "seed": args.seed,
        "minutes": None if args.cases else args.minutes,
        "results": [vars(r) for r in results],
    }


def format_result(result: dict) -> str:
    from tisem.testing.fuzz import CaseResult, summary_table

    if "replay" in result:
        r = result["replay"]
        return (
            f"{r['target']} seed {r['seed']} case {r['case']}: {r['what']}\n"
            f"input kept in {r['input']}\noutcome: {r['outcome']} {r['detail']}"
        )
    results = [CaseResult(**r) for r in result["results"]]
    budget = f"{result['minutes']} min" if result["minutes"] else "fixed cases"
    return f"fuzz campaign, {result['date']}, seed {result['seed']}, {budget}\n\n" + summary_table(
        results
    )


def main(argv: list[str] | None = None) -> int:
    return benchmark_main(argv, parse_args, run, format_result)


if __name__ == "__main__":
    sys.exit(main())
