"""Where a sweep's threads spend their time, from py-spy's collapsed stacks.

    python benchmarks/profile_summary.py PYSPY.raw [--top 30]

The runbook's `main` phase with MAIN_PYSPY=1 records the sweep process and its children with
`py-spy record --threads --idle --format raw`: one line per distinct stack, `frame;frame;...
count`, the first frame naming the process and thread. This prints, per process and thread,
the share of samples spent in each vabench function at the bottom of its stack (the innermost
vabench frame: where our code is, or what it waits on), and overall the innermost frames of any
library. Idle samples (a thread blocked in a wait) are kept: for a pipeline that waits on
itself, where it waits is the finding.
"""

from __future__ import annotations

import argparse
import re
from collections import Counter, defaultdict
from pathlib import Path

FRAME = re.compile(r"^(?P<func>[^ ]+) \((?P<file>[^:]+)(?::(?P<line>\d+))?\)$")


def parse(path: Path) -> list[tuple[list[str], int]]:
    stacks = []
    for line in path.read_text().splitlines():
        head, _, count = line.rpartition(" ")
        if not head or not count.isdigit():
            continue
        stacks.append((head.split(";"), int(count)))
    return stacks


def short(frame: str) -> str:
    m = FRAME.match(frame)
    if not m:
        return frame
    file = m["file"]
    if "vabench/" in file:
        file = "vabench/" + file.split("vabench/", 1)[1]
    else:
        parts = file.split("/")
        file = "/".join(parts[-2:])
    return f"{m['func']} ({file})"


def thread_of(frames: list[str]) -> tuple[str, str]:
    """(process, thread) from py-spy's leading frames ("process 123:..." and "thread (0x..)")."""
    process = next((f for f in frames if f.startswith("process ")), "process ?")
    thread = next((f for f in frames if f.startswith("thread ")), "thread ?")
    return process[:60], thread


def innermost_vabench(frames: list[str]) -> str | None:
    for frame in reversed(frames):
        if "vabench/" in frame:
            return short(frame)
    return None


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("raw", type=Path)
    ap.add_argument("--top", type=int, default=30)
    args = ap.parse_args()
    stacks = parse(args.raw)
    total = sum(n for _, n in stacks)
    if not total:
        raise SystemExit(f"{args.raw}: no samples")
    per_thread: dict[tuple[str, str], Counter[str]] = defaultdict(Counter)
    leaves: Counter[str] = Counter()
    for frames, n in stacks:
        body = [f for f in frames if not f.startswith(("process ", "thread "))]
        per_thread[thread_of(frames)][innermost_vabench(body) or "(outside vabench)"] += n
        if body:
            leaves[short(body[-1])] += n
    print(f"{total} samples")
    threads = sorted(per_thread.items(), key=lambda kv: -sum(kv[1].values()))
    for (process, thread), counts in threads[: args.top]:
        n = sum(counts.values())
        print(f"\n{process} {thread}: {n} samples ({100 * n / total:.1f} %)")
        for name, k in counts.most_common(8):
            print(f"  {100 * k / n:5.1f} %  {name}")
    print(f"\ninnermost frames, all threads (top {args.top}):")
    for name, k in leaves.most_common(args.top):
        print(f"  {100 * k / total:5.1f} %  {name}")


if __name__ == "__main__":
    main()
