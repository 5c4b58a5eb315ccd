"""The Warp JPEG encoder on a GPU, checked and timed alone:

    python benchmarks/warp_jpeg_check.py [--device cuda:0] [--frames 25,128] [--task T]

For each frame count, `vabench.render.warp_jpeg.WarpJpeg` encodes jpeg_contention's frames
(1280x960, ~4.5 bits a pixel at quality 95, heavier than rendered scenes) from packed pixels
on the device: ms a call on an idle GPU from one thread (min and median of 5, after a first
call that compiles), images the host had to encode, the GPU time of each kernel in one more
call (CUDA events, `wp.timing_begin`: where a pass's time goes, e.g. counting the bits against
packing them), and for the first three frames the bytes and PSNR against libjpeg-turbo's
encoding of the same pixels. The GPU under load is
jpeg_contention.py's job (`--encoder warp`).

`--task T`: the frames are instead the passive bundle of task T at its first verified seed,
rendered by the Warp renderer on `--device` (`render_rgb`: the pixels before any JPEG), encoded
by both encoders: sizes and PSNR against those pixels, for every frame.
"""

from __future__ import annotations

import argparse
import io
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp
from PIL import Image

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from jpeg_contention import frames_on_device

from vabench.render.images import ImageSettings, encode_jpeg
from vabench.render.warp_jpeg import WarpJpeg


def _psnr(decoded: np.ndarray, source: np.ndarray) -> float:
    return float(10 * np.log10(255**2 / np.mean((decoded - source.astype(float)) ** 2)))


def compare(jpegs: list[bytes], frames: np.ndarray, settings: ImageSettings) -> None:
    """Each frame's bytes and PSNR, ours against libjpeg-turbo's encoding of the same pixels."""
    for i, (jpeg, frame) in enumerate(zip(jpegs, frames, strict=True)):
        ours = np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(float)
        reference = encode_jpeg(frame, settings.quality, settings.subsampling)
        theirs = np.asarray(Image.open(io.BytesIO(reference)).convert("RGB")).astype(float)
        print(
            f"  frame {i}: {len(jpeg)} bytes (libjpeg {len(reference)}), PSNR "
            f"{_psnr(ours, frame):.2f} dB (libjpeg {_psnr(theirs, frame):.2f}), "
            f"{np.abs(ours - theirs).mean():.3f} grey levels apart on average",
            flush=True,
        )


def renders(task: str, device: str) -> None:
    """The passive bundle of `task` at its first verified seed, ray traced, both encodings."""
    import os

    from vabench.render import camera as cam
    from vabench.render.__main__ import reset_state
    from vabench.render.images import RenderItem
    from vabench.render.warp_renderer import WarpRenderPool
    from vabench.tasks.manifests import verified_seeds

    qpos, variant, gcs = reset_state(task, verified_seeds(task)[0], "c")
    arms = ("left", "right") if "handover" in task or task == "place_shoe" else ("right",)
    items = [RenderItem(qpos, variant, p) for p in cam.passive_bundle(gcs, arms)]
    settings = ImageSettings()
    os.environ["VABENCH_WARP_DEVICE"] = device
    with WarpRenderPool(jpeg="host") as pool:
        frames = pool.render_rgb(task, items, settings)
    n = len(frames)
    rgb = frames.astype(np.uint32)
    words = ((rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]).reshape(n, -1)
    jpegs = WarpJpeg(n, settings.width, settings.height, device).encode(
        wp.array(words, dtype=wp.uint32, device=device), n, settings
    )
    print(f"{task}: {n} rendered frames of {settings.width}x{settings.height}:")
    compare(jpegs, frames, settings)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--frames", default="25,128")
    ap.add_argument("--task", help="rendered frames of this task instead")
    args = ap.parse_args()
    wp.init()
    if args.task:
        renders(args.task, args.device)
        return
    settings = ImageSettings()
    for n in (int(v) for v in args.frames.split(",")):
        packed = frames_on_device(n, settings.width, settings.height, args.device, packed=True)
        rgb = frames_on_device(min(n, 3), settings.width, settings.height, "cpu").numpy()
        encoder = WarpJpeg(n, settings.width, settings.height, args.device)
        t0 = time.perf_counter()
        encoder.encode(packed, n, settings)
        first = time.perf_counter() - t0
        times = []
        for _ in range(5):
            t0 = time.perf_counter()
            out = encoder.encode(packed, n, settings)
            times.append(time.perf_counter() - t0)
        print(
            f"{n} frames: first call {first:.1f} s (compiles), then {min(times) * 1e3:.1f} ms "
            f"a call (min of 5; median {statistics.median(times) * 1e3:.1f}), "
            f"{n / min(times):.0f} images/s; encoded on the host: {encoder.host_encoded}",
            flush=True,
        )
        kernel_times(encoder, packed, n, settings)
        compare(out[: len(rgb)], rgb, settings)


def kernel_times(encoder: WarpJpeg, packed: wp.array, n: int, settings: ImageSettings) -> None:
    """One more call with every kernel and copy timed on the GPU (nothing on a CPU device)."""
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY)
    encoder.encode(packed, n, settings)
    results = wp.timing_end()
    totals: dict[str, list[float]] = {}
    for r in results:
        totals.setdefault(r.name, []).append(r.elapsed)
    if not totals:
        print("  kernels: no CUDA timings (a CPU device)", flush=True)
        return
    whole = sum(sum(v) for v in totals.values())
    for name, ms in sorted(totals.items(), key=lambda kv: -sum(kv[1])):
        print(
            f"  {name}: {sum(ms):.2f} ms in {len(ms)} call(s) ({sum(ms) / whole:.0%})", flush=True
        )


if __name__ == "__main__":
    main()
