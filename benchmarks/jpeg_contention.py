"""What a device JPEG call waits for when its process is busy: nvImageCodec under contention.

    python benchmarks/jpeg_contention.py [--images 25] [--size 1280x960] [--seconds 8]
        [--encoders 4] [--encoder nvimgcodec,nvjpeg,warp] [--busy 0,6] [--threads 0]
        [--switch 0] [--gpu-load 0,1] [--slices 1] [--json FILE]

In the main job on an H100 a JPEG call of a render pass (~25 frames of 1280x960 already in
device memory) took 0.23-0.36 s of wall time for ~3 ms of nvJPEG kernels, while three frames
encode in 15-18 ms on an idle GPU (docs/PERFORMANCE.md, "JPEG on the GPU"). This benchmark
rebuilds the engine process's conditions one at a time, each configuration in a fresh process
(Python's switch interval and nvImageCodec's thread pools are per process):

- `--encoders` threads each encode `--images` frames again and again (one encoder a thread,
  each on a stream of its own at the renderer's encode priority, as `WarpRenderPool` has);
- `--encoder`: `nvimgcodec` (`vabench.render.gpu_jpeg.DeviceJpeg`: nvImageCodec, which encodes
  on default-priority streams of its own) or `nvjpeg` (`vabench.render.nvjpeg.NvJpeg`: nvJPEG
  on the thread's stream) or `warp` (`vabench.render.warp_jpeg.WarpJpeg`: our own kernels on
  a stream of their own, two waits a call, from the pass's packed pixels);
- `--busy` other Python threads keep the interpreter's lock busy (pure-Python work, as the
  engine's event loop, request building and other render threads do);
- `--threads`: each encoder's host threads (nvImageCodec's `max_num_cpu_threads`; 0 is its
  default, the host's cores less one: a pool woken for every call; nvimgcodec only);
- `--switch`: Python's switch interval (0: the default 5 ms): the binding hands the lock back
  and forth ~3 times an image, and each hand-off can wait one interval;
- `--slices`: nvJPEG only: each call's frames cut into up to this many slices encoded side by
  side, each with an encoder and a stream of its own (`encode_in_slices`);
- `--gpu-load 1`: a thread keeps every SM busy with kernels of many blocks on a non-blocking
  stream of the least priority, eight queued at a time (the ray tracer's megakernels of other
  passes), so that the GPU never idles between them.

Prints, per configuration, JPEG calls a second, images a second and the median and 90th
percentile wall time of a call. Run it on the GPU (`bash benchmarks/gpu/run.sh jpeg`).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import json
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import Executor, ThreadPoolExecutor, wait
from pathlib import Path
from typing import Any

import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


@wp.kernel
def _spin(a: wp.array(dtype=wp.float32), n: int):  # type: ignore[valid-type]
    """GPU load: a long arithmetic loop a thread (the ray tracer's megakernels, stand-in)."""
    i = wp.tid()
    v = a[i]
    for _ in range(n):
        v = v * 0.999 + 0.001
    a[i] = v


MIN_SLICE = 4
"""Fewest frames of a slice (`encode_in_slices`)."""


def slice_bounds(n: int, slices: int, least: int = MIN_SLICE) -> list[tuple[int, int]]:
    """[start, stop) of `n` frames cut into at most `slices` runs of nearly equal length, none
    shorter than `least` (one run for fewer than 2 x `least` frames)."""
    k = max(1, min(slices, n // max(1, least)))
    step, extra = divmod(n, k)
    bounds, start = [], 0
    for i in range(k):
        stop = start + step + (i < extra)
        bounds.append((start, stop))
        start = stop
    return bounds


def encode_in_slices(
    encode: Callable[[int, int, int], list[bytes]], n: int, slices: int, pool: Executor | None
) -> list[bytes]:
    """`n` frames' JPEGs in order, their `slice_bounds` encoded side by side: `encode(i, start,
    stop)` for slice i, the first in this thread and the others in `pool`'s threads (each with
    an encoder and a stream of its own). Every slice has ended when this returns or raises.
    The question it answers: an nvJPEG encode call returns only after its frame's GPU pass
    (in the main job the stream's wait after the calls found nothing left), so would one
    call's frames in slices overlap on the GPU? Measured on an H100 (2026-11-27): no (under
    the GPU load 0.223 s a call in one slice, 0.216 in 2, 0.486 in 4), so the renderer has no
    such option."""
    bounds = slice_bounds(n, slices) if pool is not None else [(0, n)]
    futures = [pool.submit(encode, i, *b) for i, b in enumerate(bounds[1:], 1)] if pool else []
    try:
        out = encode(0, *bounds[0])
    finally:
        wait(futures)
    for future in futures:
        out += future.result()
    return out


def frames_on_device(n: int, width: int, height: int, device: str, packed: bool = False):
    """`n` frames (smooth shading, edges and noise: ~4.5 bits a pixel at quality 95, rendered
    scenes ~1-1.5), as (n, H, W, 3) bytes or, `packed`, as a render pass holds them: (n, H * W)
    uint32 0x00RRGGBB."""
    import numpy as np

    rng = np.random.default_rng(0)
    y, x = np.mgrid[0:height, 0:width].astype(np.float32)
    base = np.stack([x / width, y / height, 0.5 + 0.5 * np.sin(x / 37.0) * np.cos(y / 53.0)], -1)
    out = np.empty((n, height, width, 3), np.uint8)
    for i in range(n):
        img = 200 * base + 20 * rng.standard_normal((height, width, 1)).astype(np.float32)
        img[(x.astype(int) // (40 + i)) % 7 == 0] = 30  # edges
        out[i] = np.clip(img, 0, 255).astype(np.uint8)
    if packed:
        rgb = out.astype(np.uint32)
        words = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
        return wp.array(words.reshape(n, height * width), dtype=wp.uint32, device=device)
    return wp.array(out, dtype=wp.uint8, device=device)


def encoder_call(
    args: argparse.Namespace, cuda: Any, frames: Any, settings: Any, device_lock: Any
) -> tuple[Callable[[], list[bytes]], ThreadPoolExecutor | None]:
    """One encoder thread's call (every frame encoded once) and its slices' helper threads.
    `device_lock`: held around Warp launches (Warp's current stream is one a device for the
    whole process: threads switching it at once would put kernels on each other's streams; the
    renderer holds its device lock so)."""
    from vabench.render import gpu_jpeg, nvjpeg, warp_jpeg
    from vabench.sim_mjx.warp import streams

    if args.encoder == "warp":
        height, width = settings.height, settings.width
        own = warp_jpeg.WarpJpeg(args.images, width, height, cuda, "middle")
        return (lambda: own.encode(frames, args.images, settings, lambda: device_lock)), None
    slices = args.slices if args.encoder == "nvjpeg" else 1
    # an encoder and a stream a slice (the renderer lends its encoders so)
    lent: list[tuple[Any, int]] = []
    for _ in range(slices):
        stream = streams.new_stream(cuda, "middle")
        assert stream is not None
        jpeg: Any = (
            nvjpeg.NvJpeg(0)
            if args.encoder == "nvjpeg"
            else gpu_jpeg.DeviceJpeg(0, threads=args.threads)
        )
        lent.append((jpeg, stream.cuda_stream))
    helpers = ThreadPoolExecutor(slices - 1) if slices > 1 else None

    def encode(i: int, start: int, stop: int) -> list[bytes]:
        jpeg, stream = lent[i]
        with cuda.context_guard:
            return jpeg.encode(frames[start:stop], settings, stream)

    return (lambda: encode_in_slices(encode, args.images, slices, helpers)), helpers


def one_configuration(args: argparse.Namespace) -> dict:
    """Runs in a child process: one configuration, timed for `args.seconds`."""
    if args.switch > 0:
        sys.setswitchinterval(args.switch)
    wp.init()
    from vabench.render.images import ImageSettings
    from vabench.sim_mjx.warp import streams

    width, height = (int(v) for v in args.size.split("x"))
    device = args.device
    frames = frames_on_device(args.images, width, height, device, args.encoder == "warp")
    settings = ImageSettings(width=width, height=height)
    stop = threading.Event()
    calls: list[float] = []
    lock = threading.Lock()
    device_lock = threading.Lock()  # Warp's launches (see encoder_call)
    sizes: list[int] = []
    errors: list[str] = []
    # every encoder after its warm-up encode, the GPU load after its first kernels, and this
    # thread: the timing starts when all are running (a first encode or kernel compiles)
    ready = threading.Barrier(args.encoders + (1 if args.gpu_load else 0) + 1, timeout=120)

    def failing(target):
        def run() -> None:
            try:
                target()
            except BaseException as err:  # reported by the child's exit status
                errors.append(f"{target.__name__}: {err!r}")
                ready.abort()
                stop.set()

        return run

    def encoder_thread() -> None:
        with wp.ScopedDevice(device):
            cuda = wp.get_device(device)
            call, helpers = encoder_call(args, cuda, frames, settings, device_lock)
            call()  # warm-up (the first compiles or allocates)
            ready.wait()
            while not stop.is_set():
                t0 = time.perf_counter()
                out = call()
                with lock:
                    calls.append(time.perf_counter() - t0)
                    sizes.append(len(out[0]))
            if helpers is not None:
                helpers.shutdown()

    def busy_thread() -> None:
        x = 0
        while not stop.is_set():
            for i in range(2000):
                x += i * i % 7

    def gpu_load_thread() -> None:
        # like the ray tracer's passes: a non-blocking stream at the least priority, kernels of
        # many blocks (16 waves of the H100's 132 SMs x 2,048 threads, each thread ~0.5 ms),
        # eight queued at a time so that the SMs never wait for the host
        with wp.ScopedDevice(device):
            stream = streams.new_stream(wp.get_device(device), "least")
            assert stream is not None
            a = wp.zeros(132 * 2048 * 16, dtype=wp.float32)
            first = True
            while not stop.is_set():
                with device_lock, wp.ScopedStream(stream):
                    for _ in range(8):
                        wp.launch(_spin, dim=a.shape[0], inputs=[a, 200_000])
                wp.synchronize_stream(stream)
                if first:
                    ready.wait()
                    first = False

    workers = [threading.Thread(target=failing(encoder_thread)) for _ in range(args.encoders)]
    workers += [threading.Thread(target=failing(busy_thread)) for _ in range(args.busy)]
    if args.gpu_load:
        workers.append(threading.Thread(target=failing(gpu_load_thread)))
    for t in workers:
        t.start()
    with contextlib.suppress(threading.BrokenBarrierError):  # a thread failed: `errors`
        ready.wait()
    with lock:
        calls.clear()
    t0 = time.perf_counter()
    stop.wait(args.seconds)
    with lock:
        timed = list(calls)
    elapsed = time.perf_counter() - t0
    stop.set()
    for t in workers:
        t.join()
    if errors:
        print("\n".join(errors), file=sys.stderr)
        sys.exit(1)
    timed.sort()
    return {
        "calls_per_s": len(timed) / elapsed,
        "images_per_s": len(timed) * args.images / elapsed,
        "median_s": statistics.median(timed) if timed else None,
        "p90_s": timed[int(0.9 * (len(timed) - 1))] if timed else None,
        "calls": len(timed),
        "jpeg_bytes": sizes[-1] if sizes else None,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--images", type=int, default=25)
    ap.add_argument("--size", default="1280x960")
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--encoders", type=int, default=4)
    ap.add_argument("--encoder", default="nvimgcodec,nvjpeg")
    ap.add_argument("--busy", default="0,6")
    ap.add_argument("--threads", default="0")
    ap.add_argument("--switch", default="0")
    ap.add_argument("--gpu-load", default="0,1")
    ap.add_argument("--slices", default="1")
    ap.add_argument("--device", default="cuda:0", help="cpu: a smoke check of --encoder warp")
    ap.add_argument("--json", type=Path)
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args, _ = ap.parse_known_args()
    if args.child:
        args.busy, args.threads, args.switch, args.gpu_load = (
            int(args.busy),
            int(args.threads),
            float(args.switch),
            int(args.gpu_load),
        )
        args.slices = int(args.slices)
        print(json.dumps(one_configuration(args)))
        return
    grid = itertools.product(
        args.encoder.split(","),
        [int(v) for v in args.gpu_load.split(",")],
        [int(v) for v in args.busy.split(",")],
        [int(v) for v in args.threads.split(",")],
        [float(v) for v in args.switch.split(",")],
        [int(v) for v in args.slices.split(",")],
    )
    print(
        f"{args.encoders} encoder threads, {args.images} frames of {args.size} a call, "
        f"{args.seconds:g} s each"
    )
    print(
        f"{'encoder':>10} {'gpu load':>8} {'busy':>4} {'threads':>7} {'switch ms':>9} "
        f"{'slices':>6} {'calls/s':>8} {'img/s':>7} {'median s':>8} {'p90 s':>7}"
    )
    rows = []
    for encoder, gpu_load, busy, threads, switch, slices in grid:
        if slices > 1 and encoder != "nvjpeg":
            continue  # slices are nvJPEG's
        row = f"{encoder:>10} {gpu_load:>8} {busy:>4} {threads:>7} {switch * 1e3:>9g} {slices:>6}"
        cmd = [
            sys.executable, __file__, "--child", "--images", str(args.images), "--size", args.size,
            "--seconds", str(args.seconds), "--encoders", str(args.encoders), "--busy", str(busy),
            "--threads", str(threads), "--switch", str(switch), "--gpu-load", str(gpu_load),
            "--encoder", encoder, "--slices", str(slices), "--device", args.device,
        ]  # fmt: skip
        try:
            done = subprocess.run(
                cmd, capture_output=True, text=True, timeout=240 + 2 * args.seconds
            )
        except subprocess.TimeoutExpired:
            print(f"{row} timed out")
            continue
        lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
        if done.returncode != 0 or not lines:
            print(f"{row} failed: {(done.stderr or done.stdout).strip().splitlines()[-1:]}")
            continue
        r = json.loads(lines[-1])
        r.update(
            encoder=encoder,
            gpu_load=gpu_load,
            busy=busy,
            threads=threads,
            switch_s=switch,
            slices=slices,
        )
        rows.append(r)
        print(
            f"{row} {r['calls_per_s']:>8.1f} {r['images_per_s']:>7.0f} "
            f"{r['median_s'] or 0:>8.3f} {r['p90_s'] or 0:>7.3f}",
            flush=True,
        )
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
