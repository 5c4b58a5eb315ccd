"""Where an engine process's GPU time goes, kernel by kernel: a window of CUDA activity
recorded by NVIDIA's CUPTI (through PyTorch's profiler, which the GPU image has), summed by
kernel and by stage.

Why: the GPU sampler (`gpu_busy`) says whether a kernel ran, not whose. The warm suite keeps
the GPU nearly always busy while a physics call of a few dozen worlds takes far longer than its
kernels: which of physics, ray tracing, JPEG and copies fills the GPU decides where to cut
(docs/PERFORMANCE.md, "Whole suite on one GPU"), and a GPU host need not have a profiler.
CUPTI records every kernel of the process whoever launched it (Warp, its CUDA graphs' nodes,
nvImageCodec), with its time on the GPU.

Set `VABENCH_KERNEL_PROFILE` to a folder (and `VABENCH_KERNEL_PROFILE_AT` / `_S`, seconds
after the process's chunk starts / of the window; 60 and 20 by default): each engine worker
of the processes executor writes `kernels_<pid>.json` there (`record_in_background`), with the
window's seconds, each kernel's calls and GPU microseconds, and the sums per stage
(`stage_of`). `python -m vabench.tuning.kernel_profile FOLDER` prints them, every process
together. Recording costs the process time (each kernel's record), so a profiled run is not a
timing run. Without PyTorch, or where CUPTI cannot record, the file says why instead.
"""

from __future__ import annotations

import json
import os
import re
import sys
import threading
import time
from collections import Counter
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

from vabench import switches

FOLDER_VARIABLE = switches.variable("kernel_profile")
AT_VARIABLE = switches.variable("kernel_profile_at")
SECONDS_VARIABLE = switches.variable("kernel_profile_s")
DEFAULT_AT_S = switches.SWITCHES["kernel_profile_at"].default
DEFAULT_S = switches.SWITCHES["kernel_profile_s"].default

WARP_JPEG_KERNELS = (
    "_transform",
    "_count_bits",
    "_pack",
    "_count_ff",
    "_sizes",
    "_place",
    "_kernels__locals__totals",
    "_kernels__locals__scan",
)
"""The renderer's own JPEG kernels (`vabench.render.warp_jpeg`, and `warp_scan`'s, made in its
`_kernels`): Warp names a kernel's CUDA function `<name>_<8 hex of its hash>_cuda_kernel_...`,
so they are told apart from MuJoCo Warp's by the whole name, not a word of it
(tests/test_kernel_profile.py checks every kernel of those modules is listed)."""
_WARP_JPEG = re.compile(rf"^(?:{'|'.join(WARP_JPEG_KERNELS)})_[0-9a-f]{{8}}_cuda_kernel_")

STAGES: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("copies", ("memcpy", "memset")),
    ("jpeg", ("nvjpeg", "jpeg", "huffman", "dct", "nvimgcodec")),
    ("render", ("render", "bvh", "_place_cameras", "_unpack_rgb", "camlight", "refit")),
    ("physics", ("mujoco_warp", "vabench", "warp", "cuda_kernel_forward")),
)
"""A kernel's stage: "jpeg" for the renderer's own JPEG kernels (`WARP_JPEG_KERNELS`), else the
first whose words its name (lower case) contains; else "other". Kinematics launched by a render
pass count as physics (same kernels as the physics')."""


def stage_of(name: str) -> str:
    if _WARP_JPEG.match(name):
        return "jpeg"
    low = name.lower()
    for stage, words in STAGES:
        if any(w in low for w in words):
            return stage
    return "other"


def summarize(kernels: Mapping[str, tuple[int, float]], window_s: float) -> dict[str, Any]:
    """The file's content from {kernel name: (calls, GPU microseconds)} over `window_s`."""
    stages: dict[str, float] = {}
    for name, (_, us) in kernels.items():
        stages[stage_of(name)] = stages.get(stage_of(name), 0.0) + us
    ranked = sorted(stages.items(), key=lambda kv: -kv[1])
    return {
        "window_s": window_s,
        "gpu_s": sum(stages.values()) / 1e6,
        "stages_s": {k: v / 1e6 for k, v in ranked},
        "kernels": {
            name: {"calls": calls, "us": round(us, 1)}
            for name, (calls, us) in sorted(kernels.items(), key=lambda kv: -kv[1][1])
        },
    }


def _record(seconds: float) -> dict[str, tuple[int, float]]:
    """Every kernel and copy of this process for `seconds` (CUPTI through PyTorch)."""
    from torch.profiler import ProfilerActivity, profile

    prof = profile(activities=[ProfilerActivity.CUDA])
    prof.start()
    time.sleep(seconds)
    prof.stop()
    calls: Counter[str] = Counter()
    us: dict[str, float] = {}
    for event in prof.events():
        if getattr(event.device_type, "name", "") != "CUDA":
            continue
        spent = getattr(event, "device_time_total", None)
        if spent is None:  # older PyTorch
            spent = event.cuda_time_total
        calls[event.name] += 1
        us[event.name] = us.get(event.name, 0.0) + float(spent)
    return {name: (calls[name], us[name]) for name in calls}


def record_in_background(environ: Mapping[str, str] = os.environ) -> threading.Thread | None:
    """Where `FOLDER_VARIABLE` is set: a daemon thread that waits `AT_VARIABLE` seconds, records
    `SECONDS_VARIABLE` seconds of this process's kernels and writes `kernels_<pid>.json` (or,
    when recording fails, the reason) into the folder. None where it is not set."""
    folder = switches.get("kernel_profile", environ)
    if not folder:
        return None
    at = float(switches.get("kernel_profile_at", environ))
    seconds = float(switches.get("kernel_profile_s", environ))
    path = Path(folder) / f"kernels_{os.getpid()}.json"

    def run() -> None:
        time.sleep(at)
        try:
            out = summarize(_record(seconds), seconds)
        except Exception as err:  # no PyTorch, no CUPTI, CUPTI refused under MPS...
            out = {"error": f"{type(err).__name__}: {err}"}
        out["pid"], out["at_s"] = os.getpid(), at
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(out, indent=1))

    thread = threading.Thread(target=run, name="kernel-profile", daemon=True)
    thread.start()
    return thread


def report(files: Iterable[Path]) -> str:
    """Every process's window, then the stages and the 25 costliest kernels of all of them."""
    lines, stages, kernels = [], Counter[str](), Counter[str]()
    calls = Counter[str]()
    for path in sorted(files):
        data = json.loads(path.read_text())
        if "error" in data:
            lines.append(f"{path.name}: {data['error']}")
            continue
        share = data["gpu_s"] / data["window_s"] if data["window_s"] else 0.0
        parts = ", ".join(f"{k} {v:.2f} s" for k, v in data["stages_s"].items())
        lines.append(
            f"{path.name}: {data['gpu_s']:.2f} s of kernels in {data['window_s']:.0f} s "
            f"({share:.0%} of the GPU's time if run alone): {parts}"
        )
        stages.update(data["stages_s"])
        for name, k in data["kernels"].items():
            kernels[name] += k["us"]
            calls[name] += k["calls"]
    total = sum(stages.values())
    if total:
        lines.append(
            "all: " + ", ".join(f"{k} {v:.2f} s ({v / total:.0%})" for k, v in stages.most_common())
        )
        for name, us in kernels.most_common(25):
            mean = us / calls[name]
            lines.append(
                f"  {us / 1e6:8.3f} s {calls[name]:9d} calls {mean:9.1f} us  "
                f"{stage_of(name):8s} {name[:90]}"
            )
    return "\n".join(lines)


if __name__ == "__main__":
    folder = Path(sys.argv[1] if len(sys.argv) > 1 else ".")
    print(report(folder.glob("kernels_*.json")))
