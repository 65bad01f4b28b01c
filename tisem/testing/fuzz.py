"""Seeded fuzz campaigns over damaged MCAP recordings and SemanticKITTI folders.

Case `i` of seed `s` is fully determined by (target, s, i): its random choices come from
`numpy.random.default_rng([s, i])`, so a failure is replayed with `replay(target, s, i)`.
Cases run in a worker process (`python -m tisem.testing.fuzz WORKER-ARGS`) that limits its own
memory (a length taken on trust that allocates gigabytes is a failure, not a swapping
machine) and each case's time; when the worker dies of a signal, that case is a failure and a
new worker goes on with the next one. Each case is judged by `tisem.testing.oracle`.
"""

from __future__ import annotations

import json
import os
import re
import resource
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections import Counter
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from tisem.testing.oracle import OUTCOMES, Outcome

TARGETS = ("mcap", "kitti", "rosbag")
MEMORY_LIMIT_MB = 3072
CASE_TIMEOUT_S = 30


@dataclass
class CaseResult:
    target: str
    seed: int
    case: int
    what: str
    outcome: str  # one of tisem.testing.oracle.OUTCOMES
    detail: str = ""

    def line(self) -> str:
        return (
            f"{self.target} seed {self.seed} case {self.case}: {self.what} -> "
            f"{self.outcome}{': ' + self.detail if self.detail else ''}"
        )


class _Target:
    """The intact inputs of one target, their scans, and its cases."""

    def __init__(self, name: str, folder: Path) -> None:
        from tisem.io.semantickitti import SemanticKittiSequence
        from tisem.testing import kitti_damage, mcap_damage
        from tisem.testing.oracle import reference

        self.name, self.folder = name, folder
        if name == "kitti":
            self.base = kitti_damage.write_base(folder / "intact")
            self.ref = reference(SemanticKittiSequence(self.base))
            return
        from tisem.io.bag_open import open_scan_reader
        from tisem.testing import bag_damage

        # (recordings are opened as a user opens them: a per-message split by its folder)
        writer = mcap_damage if name == "mcap" else bag_damage
        self.bases = writer.write_bases(folder)
        self.refs = {b: reference(open_scan_reader(base.path)) for b, base in self.bases.items()}

    def mutation(self, seed: int, case: int):
        from tisem.testing import kitti_damage, mcap_damage

        rng = np.random.default_rng([seed, case])
        if self.name == "mcap":
            return mcap_damage.mcap_mutation(self.bases, rng, case)
        if self.name == "rosbag":
            from tisem.testing import bag_damage

            return bag_damage.bag_mutation(self.bases, rng, case)
        return kitti_damage.kitti_mutation(rng, case)

    def case_path(self, mutation, case: int) -> Path:
        """Where case `case` is built (a per-message MCAP split in its rosbag2 folder)."""
        if self.name == "mcap":
            from tisem.testing.mcap_damage import case_folder

            return case_folder(self.folder, mutation.base) / f"case{case}.mcap"
        if self.name == "rosbag":
            return self.folder / f"case{case}.bag"
        return self.folder / f"case{case}"

    def build(self, mutation, case: int) -> Path:
        path = self.case_path(mutation, case)
        mutation.write(self.base if self.name == "kitti" else self.bases, path)
        return path

    def judge(self, mutation, path: Path) -> Outcome:
        from tisem.testing.oracle import judge_bag, judge_kitti

        if self.name == "kitti":
            return judge_kitti(path, self.ref, mutation.detectable)
        return judge_bag(path, self.refs[mutation.base], mutation.detectable)


def _remove(path: Path) -> None:
    if path.is_dir():
        import shutil

        shutil.rmtree(path, ignore_errors=True)
    elif path.exists():
        path.unlink()


class _Timeout(Exception):
    pass


class _BuildFailed(Exception):
    pass


def _on_alarm(signum, frame):
    raise _Timeout()


def _worker(
    target: str,
    seed: int,
    start: int,
    count: int,
    deadline: float,
    memory_mb: int,
    case_timeout_s: int,
    crash_case: int,
) -> None:
    """Run cases start, start+1, ... and print one JSON line before and after each.
    `crash_case` (>= 0) makes the worker die of SIGSEGV in that case: how the harness itself
    is tested."""
    limit = memory_mb << 20
    resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    signal.signal(signal.SIGALRM, _on_alarm)

    def emit(**fields) -> None:
        print(json.dumps(fields), flush=True)

    with tempfile.TemporaryDirectory(prefix="tisem-fuzz-") as tmp:
        runner = _Target(target, Path(tmp))
        case = start
        while (count < 0 or case < start + count) and (deadline == 0 or time.time() < deadline):
            emit(case=case)
            mutation = runner.mutation(seed, case)
            emit(case=case, what=f"[{getattr(mutation, 'base', 'folder')}] {mutation.what}")
            if case == crash_case:
                os.kill(os.getpid(), signal.SIGSEGV)
            signal.alarm(case_timeout_s)
            try:
                try:
                    path = runner.build(mutation, case)
                except Exception as e:  # noqa: BLE001 - a fault of the mutation, said as such
                    raise _BuildFailed(f"{type(e).__name__}: {e}") from None
                outcome = runner.judge(mutation, path)
            except _BuildFailed as e:
                outcome = Outcome("failure", f"the damaged input could not be built ({e})")
            except _Timeout:
                outcome = Outcome("failure", f"no result within {case_timeout_s} s")
            except MemoryError:
                outcome = Outcome("failure", f"MemoryError (limit {memory_mb} MB)")
            finally:
                signal.alarm(0)
            emit(case=case, outcome=outcome.kind, detail=outcome.detail)
            _remove(runner.case_path(mutation, case))
            case += 1


def run_campaign(
    target: str,
    seed: int,
    count: int | None = None,
    minutes: float | None = None,
    memory_mb: int = MEMORY_LIMIT_MB,
    case_timeout_s: int = CASE_TIMEOUT_S,
    crash_case: int | None = None,
) -> list[CaseResult]:
    """`count` cases (or as many as `minutes` allow) of `target`, each in a worker process
    (`crash_case`: see `_worker`)."""
    if target not in TARGETS:
        raise ValueError(f"target must be one of {TARGETS}, got {target!r}")
    deadline = time.time() + 60 * minutes if minutes else 0.0
    results: list[CaseResult] = []
    case, end = 0, count
    root = str(Path(__file__).resolve().parents[2])
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([root, *filter(None, [os.environ.get("PYTHONPATH")])]),
        "OPENBLAS_NUM_THREADS": "1",
    }
    while end is None or case < end:
        if deadline and time.time() >= deadline:
            break
        todo = -1 if end is None else end - case
        with tempfile.TemporaryFile("w+") as err:
            proc = subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "tisem.testing.fuzz",
                    target,
                    str(seed),
                    str(case),
                    str(todo),
                    str(deadline),
                    str(memory_mb),
                    str(case_timeout_s),
                    str(-1 if crash_case is None else crash_case),
                ],
                stdout=subprocess.PIPE,
                stderr=err,
                text=True,
                env=env,
            )
            current, what = _collect(proc, seed, target, results, 4 * case_timeout_s + 60)
            rc = proc.wait()
            if current is None and rc == 0:
                break
            if current is None:
                err.seek(0)
                raise RuntimeError(
                    f"the fuzz worker failed outside a case (exit {rc}): {err.read()[-2000:]}"
                )
            why = (
                f"the reader process died of {signal.Signals(-rc).name}"
                if rc < 0
                else f"the reader process exited with {rc}"
            )
            results.append(CaseResult(target, seed, current, what or "?", "failure", why))
            case = current + 1
    return results


def _collect(
    proc: subprocess.Popen, seed: int, target: str, results: list, silence_s: float
) -> tuple[int | None, str | None]:
    """Read the worker's lines into `results`; returns the case it was in when it stopped
    (None when it finished its cases). A worker silent for `silence_s` is killed."""
    current, what = None, None
    watchdog = threading.Timer(silence_s, proc.kill)
    watchdog.start()
    try:
        for line in proc.stdout:
            watchdog.cancel()
            watchdog = threading.Timer(silence_s, proc.kill)
            watchdog.start()
            msg = json.loads(line)
            if "outcome" in msg:
                results.append(
                    CaseResult(target, seed, msg["case"], what, msg["outcome"], msg["detail"])
                )
                current, what = None, None
            elif "what" in msg:
                what = msg["what"]
            else:
                current = msg["case"]
    finally:
        watchdog.cancel()
    return current, what


def replay(target: str, seed: int, case: int, folder: Path) -> tuple[str, Path, Outcome]:
    """One case in this process: (what was done, the damaged input kept in `folder`, outcome)."""
    runner = _Target(target, Path(folder))
    mutation = runner.mutation(seed, case)
    path = runner.build(mutation, case)
    return mutation.what, path, runner.judge(mutation, path)


def summary_table(results: list[CaseResult]) -> str:
    """Cases and outcomes per target as a Markdown table, then the failures: grouped by the
    kind of mutation (numbers left out), each with how many and its first seed and case."""
    head = "| target | cases | " + " | ".join(OUTCOMES) + " |\n|---|---:|" + "---:|" * len(OUTCOMES)
    rows = []
    for target in TARGETS:
        mine = [r for r in results if r.target == target]
        if mine:
            counts = Counter(r.outcome for r in mine)
            rows.append(
                f"| {target} | {len(mine)} | " + " | ".join(str(counts[o]) for o in OUTCOMES) + " |"
            )
    kinds: dict[str, list[CaseResult]] = {}
    for r in results:
        if r.outcome == "failure":
            kinds.setdefault(re.sub(r"\d+", "N", f"{r.target}: {r.what}"), []).append(r)
    failures = [f"{len(rs)} x {kind} (first: {rs[0].line()})" for kind, rs in kinds.items()]
    return "\n".join([head, *rows] + (["", "failures:", *failures] if failures else []))


if __name__ == "__main__":
    name, seed_, start_, count_, deadline_, memory_, timeout_, crash_ = sys.argv[1:9]
    _worker(
        name,
        int(seed_),
        int(start_),
        int(count_),
        float(deadline_),
        int(memory_),
        int(timeout_),
        int(crash_),
    )
