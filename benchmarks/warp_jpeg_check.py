"""GPU check of warp_jpeg: the benchmark's frames on cuda:0, decoded and compared with libjpeg-turbo."""
import io, sys, time
import numpy as np, warp as wp
sys.path.insert(0, "benchmarks")
from PIL import Image
from jpeg_contention import frames_on_device
from vabench.render.images import ImageSettings, encode_jpeg
from vabench.render.warp_jpeg import WarpJpeg
wp.init()
for n in (25, 128):
    packed = frames_on_device(n, 1280, 960, "cuda:0", packed=True)
    rgb = frames_on_device(min(n, 3), 1280, 960, "cpu").numpy()
    enc = WarpJpeg(n, 1280, 960, "cuda:0")
    s = ImageSettings()
    enc.encode(packed, n, s)
    times = []
    for _ in range(5):
        t = time.perf_counter(); out = enc.encode(packed, n, s); times.append(time.perf_counter() - t)
    print(f"n={n}: idle GPU, one thread: {min(times)*1e3:.1f} ms a call (min of 5), {np.median(times)*1e3:.1f} median; host_encoded {enc.host_encoded}; bytes {len(out[0])}")
    for i in range(min(n, 3)):
        dec = np.asarray(Image.open(io.BytesIO(out[i])).convert("RGB")).astype(float)
        ref = encode_jpeg(rgb[i], 95, "420")
        refd = np.asarray(Image.open(io.BytesIO(ref)).convert("RGB")).astype(float)
        psnr = lambda a: 10 * np.log10(255**2 / np.mean((a - rgb[i]) ** 2))
        print(f"  frame {i}: {len(out[i])} bytes (libjpeg {len(ref)}), PSNR {psnr(dec):.2f} dB (libjpeg {psnr(refd):.2f}), mean |diff| to libjpeg's {np.abs(dec-refd).mean():.3f}")
