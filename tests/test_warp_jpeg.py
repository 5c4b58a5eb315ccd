"""JPEG in Warp kernels (`vabench.render.warp_jpeg`) on Warp's CPU device, the kernels a GPU
runs, checked against libjpeg-turbo (`images.encode_jpeg`, the host path's encoder).

What is checked: the tables are libjpeg's (quantisation at every quality, Huffman, zigzag);
frames of several sizes, subsamplings and qualities decode to the pixels libjpeg's own JPEGs
decode to, within rounding, at the same quality (PSNR) and about the same size; every image of
a batch is independent of the others; the bytes are those of the encoder before the
coefficients were kept between its kernels (goldens); 0xFF bytes are stuffed; an image too
large for the device's buffer is encoded on the host, in its place; the renderer with
`jpeg="kernels"` gives images equal to its host-encoded ones within rounding. Speed is
measured on a GPU by benchmarks/jpeg_contention.py (`--encoder warp`), never here.
"""

from __future__ import annotations

import io
import os

import numpy as np
import pytest
from PIL import Image

pytest.importorskip("warp", reason="warp_jpeg needs warp-lang (the [test] extra has it)")

import warp as wp

from vabench.render import warp_jpeg
from vabench.render.images import ImageSettings, encode_jpeg


def _decode(jpeg: bytes) -> np.ndarray:
    return np.asarray(Image.open(io.BytesIO(jpeg)).convert("RGB")).astype(np.float64)


def _segments(jpeg: bytes) -> dict[int, list[bytes]]:
    """Marker -> payloads of a JPEG's segments up to its scan."""
    out: dict[int, list[bytes]] = {}
    i = 2
    while i < len(jpeg):
        marker, length = jpeg[i + 1], int.from_bytes(jpeg[i + 2 : i + 4], "big")
        out.setdefault(marker, []).append(jpeg[i + 4 : i + 2 + length])
        if marker == 0xDA:
            break
        i += 2 + length
    return out


def _scenes(n: int, height: int, width: int, seed: int = 0) -> np.ndarray:
    """Frames like a rendered scene: smooth shading, hard edges of saturated colour, a little
    noise; each frame different."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width].astype(np.float64)
    frames = np.empty((n, height, width, 3), np.uint8)
    for i in range(n):
        img = np.stack(
            [
                120 + 100 * np.sin(x / (9 + i)),
                90 + 80 * np.cos(y / 7.0),
                60 + 1.5 * (x + y) * (i + 1) % 180,
            ],
            -1,
        )
        img[height // 5 : height // 2, width // 4 : width // 2 + i] = (230, 25, 20)
        img += 3 * rng.standard_normal((height, width, 1))
        frames[i] = np.clip(img, 0, 255).astype(np.uint8)
    return frames


def _packed(frames: np.ndarray) -> wp.array:
    rgb = frames.astype(np.uint32)
    words = (rgb[..., 0] << 16) | (rgb[..., 1] << 8) | rgb[..., 2]
    return wp.array(words.reshape(len(frames), -1), dtype=wp.uint32, device="cpu")


def _psnr(a: np.ndarray, b: np.ndarray) -> float:
    return float(10 * np.log10(255**2 / np.mean((a - b.astype(np.float64)) ** 2)))


@pytest.mark.parametrize("quality", [10, 50, 75, 95, 100])
def test_the_tables_are_libjpeg_s(quality):
    ours = warp_jpeg.jpeg_header(48, 32, ImageSettings(48, 32, quality, "420"))
    theirs = encode_jpeg(np.zeros((32, 48, 3), np.uint8), quality, "420")
    for marker in (0xDB, 0xC4):  # quantisation, Huffman: the same tables, any segmenting
        assert b"".join(_segments(ours)[marker]) == b"".join(_segments(theirs)[marker])
    assert _segments(ours)[0xC0] == _segments(theirs)[0xC0]  # the frame: size, sampling


def test_zigzag_is_t81_s():
    assert warp_jpeg.ZIGZAG[:16].tolist() == [
        0,
        1,
        8,
        16,
        9,
        2,
        3,
        10,
        17,
        24,
        32,
        25,
        18,
        11,
        4,
        5,
    ]
    assert sorted(warp_jpeg.ZIGZAG.tolist()) == list(range(64))
    assert warp_jpeg.ZIGZAG[-4:].tolist() == [47, 55, 62, 63]


@pytest.mark.parametrize(
    "size, subsampling, quality",
    [((70, 45), "420", 95), ((64, 48), "422", 80), ((33, 17), "444", 100), ((96, 64), "420", 50)],
)
def test_frames_decode_to_libjpeg_s_pixels(size, subsampling, quality):
    """Sizes off the MCU grid (edges repeated), each subsampling; three frames in one call."""
    width, height = size
    frames = _scenes(3, height, width)
    settings = ImageSettings(width, height, quality, subsampling)
    out = warp_jpeg.WarpJpeg(3, width, height, "cpu").encode(_packed(frames), 3, settings)
    assert len(out) == 3
    for frame, jpeg in zip(frames, out, strict=True):
        assert jpeg[:2] == b"\xff\xd8" and jpeg[-2:] == b"\xff\xd9"
        img = Image.open(io.BytesIO(jpeg))
        assert img.size == (width, height) and img.format == "JPEG"
        reference = encode_jpeg(frame, quality, subsampling)
        ours, theirs = _decode(jpeg), _decode(reference)
        # float colour conversion and DCT against libjpeg's integer ones: rounding apart
        assert _psnr(ours, frame) > _psnr(theirs, frame) - 0.5
        error, their_error = np.abs(ours - frame).mean(), np.abs(theirs - frame).mean()
        assert error < 1.1 * their_error + 0.1
        assert 0.9 < len(jpeg) / len(reference) < 1.1


def test_each_image_is_its_own():
    """An image's bytes do not depend on the others encoded with it, nor on its place."""
    frames = _scenes(4, 40, 56, seed=3)
    settings = ImageSettings(56, 40, 95, "420")
    encoder = warp_jpeg.WarpJpeg(4, 56, 40, "cpu")
    together = encoder.encode(_packed(frames), 4, settings)
    reversed_ = encoder.encode(_packed(frames[::-1].copy()), 4, settings)
    assert together == reversed_[::-1]
    first_two = encoder.encode(_packed(frames), 2, settings)  # fewer frames than worlds
    assert first_two == together[:2]


def test_encoders_in_threads_agree_with_one():
    """Four encoders in four threads, each with its own stream on a GPU (the renderer's passes,
    benchmarks/jpeg_contention.py), give the bytes one encoder gives alone. On this CPU the
    threads check the encoder's own state; on a GPU the same run found Warp's scan racing the
    streams (test_warp_scan.py)."""
    import threading

    frames = _packed(_scenes(3, 40, 56, seed=4))
    settings = ImageSettings(56, 40, 95, "420")
    alone = warp_jpeg.WarpJpeg(3, 56, 40, "cpu").encode(frames, 3, settings)
    lock, results, errors = threading.Lock(), [], []

    def work():
        try:
            encoder = warp_jpeg.WarpJpeg(3, 56, 40, "cpu")
            for _ in range(3):
                results.append(encoder.encode(frames, 3, settings, lambda: lock))
        except Exception as err:  # reported below, not lost in the thread
            errors.append(err)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not errors
    assert len(results) == 12 and all(out == alone for out in results)


def test_one_encoder_across_subsamplings_is_a_fresh_one_each_time():
    """Changing subsampling is the one path that grows an encoder's buffers and scans: its
    bytes stay a fresh encoder's."""
    frames = _packed(_scenes(3, 40, 56, seed=4))
    encoder = warp_jpeg.WarpJpeg(3, 56, 40, "cpu")
    for subsampling in ("420", "444", "422", "420", "444"):
        for n in (3, 1):
            settings = ImageSettings(56, 40, 90, subsampling)
            fresh = warp_jpeg.WarpJpeg(3, 56, 40, "cpu").encode(frames, n, settings)
            assert encoder.encode(frames, n, settings) == fresh, (subsampling, n)


def test_ff_bytes_are_stuffed():
    frames = _scenes(2, 64, 80, seed=1)
    settings = ImageSettings(80, 64, 100, "444")
    for jpeg in warp_jpeg.WarpJpeg(2, 80, 64, "cpu").encode(_packed(frames), 2, settings):
        scan = jpeg[jpeg.index(b"\xff\xda") + 14 : -2]  # the entropy data
        at = [i for i in range(len(scan)) if scan[i] == 0xFF]
        assert at, "no 0xFF byte in the entropy data: nothing tested"
        assert all(scan[i + 1] == 0 for i in at)


def test_an_image_over_the_buffer_is_encoded_on_the_host(monkeypatch):
    monkeypatch.setattr(warp_jpeg, "CAP_BITS_PER_PIXEL", 2)
    rng = np.random.default_rng(5)
    flat = np.full((40, 48, 3), 120, np.uint8)
    noise = rng.integers(0, 256, (40, 48, 3), dtype=np.uint8)  # ~8+ bits a pixel at q95
    frames = np.stack([flat, noise, flat])
    settings = ImageSettings(48, 40, 95, "420")
    encoder = warp_jpeg.WarpJpeg(3, 48, 40, "cpu")
    out = encoder.encode(_packed(frames), 3, settings)
    assert encoder.host_encoded == 1
    assert out[1] == encode_jpeg(noise, 95, "420")  # libjpeg's own bytes, in its place
    assert out[0] == out[2] and np.abs(_decode(out[0]) - 120).max() <= 1


def test_bad_calls_are_refused():
    encoder = warp_jpeg.WarpJpeg(2, 16, 16, "cpu")
    frames = _packed(_scenes(2, 16, 16))
    with pytest.raises(ValueError, match="3 frames"):
        encoder.encode(frames, 3, ImageSettings(16, 16))
    with pytest.raises(ValueError, match="for an encoder of 2 x 16x8"):
        warp_jpeg.WarpJpeg(2, 16, 8, "cpu").encode(frames, 2, ImageSettings(16, 8))


def test_the_renderer_encodes_with_it(monkeypatch):
    """`WarpRenderPool(jpeg="kernels")`: a pass's frames encoded by its own kernels, as close to
    its pixels as libjpeg's encoding of them."""
    pytest.importorskip("mujoco_warp", reason="the Warp renderer needs mujoco-warp")
    from vabench.render import camera as cam
    from vabench.render.__main__ import reset_state
    from vabench.render.images import RenderItem
    from vabench.render.warp_renderer import WarpRenderPool
    from vabench.tasks.manifests import verified_seeds

    task = "place_single_cube"
    qpos, variant, gcs = reset_state(task, verified_seeds(task)[0], "c")
    items = [RenderItem(qpos, variant, p) for p in cam.passive_bundle(gcs, ("right",))[:3]]
    settings = ImageSettings(160, 120, 95)
    monkeypatch.setenv("VABENCH_WARP_DEVICE", "cpu")
    with WarpRenderPool(max_size=(160, 120), jpeg="kernels") as pool:
        assert "Warp kernels" in (pool.info or "")
        jpegs = pool.render(task, items, settings)
        rgb = pool.render_rgb(task, items, settings)
        parts = pool._warp_jpeg_seconds  # the passes' encoders' time, for the renderer's log
        assert set(parts) == {"queueing", "waiting for the GPU", "copying out"}
        assert sum(parts.values()) > 0
    assert len(jpegs) == 3 and os.environ["VABENCH_WARP_DEVICE"] == "cpu"
    for jpeg, frame in zip(jpegs, rgb, strict=True):
        error = np.abs(_decode(jpeg) - frame).mean()
        assert error < 1.1 * np.abs(_decode(encode_jpeg(frame, 95, "420")) - frame).mean() + 0.1


GOLDEN = {
    # sha256 (first 16 hex digits) of the three JPEGs of `_golden_frames`, concatenated, as the
    # encoder that computed every block's samples and DCT in each kernel wrote them (17c55cf,
    # whose output is checked against libjpeg-turbo above): keeping the coefficients between
    # the kernels must change no bit. The frames are integer arithmetic and PCG64 integers, the
    # same on any machine; the noise frame overflows the device's buffer at the larger sizes
    # (the host path's bytes, then).
    (37, 29, "420", 50): "f5a7727c5bda50a0",
    (37, 29, "420", 95): "e4261bc089faf282",
    (37, 29, "422", 50): "9dfbf934642dcb66",
    (37, 29, "422", 95): "575ce8866e564b02",
    (37, 29, "444", 50): "02347efa5fe5200a",
    (37, 29, "444", 95): "fdfee62365a0ac29",
    (161, 120, "420", 50): "34230fed1665c079",
    (161, 120, "420", 95): "97c35619710331c2",
    (161, 120, "422", 50): "41f18a37a3a5affe",
    (161, 120, "422", 95): "ba34173777932507",
    (161, 120, "444", 50): "1c74e4706d44708d",
    (161, 120, "444", 95): "cdc79033eaffe618",
    (1280, 960, "420", 95): "ba870aa0aafdef5d",
}


def _golden_frames(width: int, height: int) -> np.ndarray:
    y, x = np.mgrid[0:height, 0:width].astype(np.int64)
    frames = np.empty((3, height, width, 3), np.uint8)
    for i in range(2):
        img = np.stack(
            [(x * (3 + i) + y) % 256, (x * y // 7 + 40 * i) % 256, (x + 2 * y) // 3 % 256], -1
        )
        img[height // 5 : height // 2, width // 4 : width // 2 + i] = (230, 25, 20)
        frames[i] = img.astype(np.uint8)
    frames[2] = np.random.default_rng(height).integers(0, 256, (height, width, 3), dtype=np.uint8)
    return frames


@pytest.mark.parametrize("size", sorted({k[:2] for k in GOLDEN}))
def test_the_bytes_are_the_golden_ones(size):
    import hashlib

    width, height = size
    frames = _golden_frames(width, height)
    encoder = warp_jpeg.WarpJpeg(len(frames), width, height, "cpu")
    for (w, h, subsampling, quality), digest in GOLDEN.items():
        if (w, h) != size:
            continue
        settings = ImageSettings(width, height, quality, subsampling)
        jpegs = encoder.encode(_packed(frames), len(frames), settings)
        got = hashlib.sha256(b"".join(jpegs)).hexdigest()[:16]
        assert got == digest, (size, subsampling, quality)


@wp.kernel
def _quantise_all(
    values: wp.array(dtype=int),
    steps: wp.array(dtype=int),
    reciprocals: wp.array(dtype=wp.int64),
    out: wp.array2d(dtype=int),
):
    i, j = wp.tid()
    out[i, j] = warp_jpeg._quantise(values[i], steps[j], reciprocals[j])


def test_quantising_without_a_division_is_libjpeg_s_rounding():
    """`_quantise` (a multiply and shifts) against round(value / (q 2^14)) with halves away
    from zero, in exact integers: every step 1-255, values over the whole range a coefficient
    can take (|value| < 2^25), the halves and their neighbours included."""
    steps = np.arange(1, 256)
    scale = 1 << int(warp_jpeg.DCT_BITS)
    rng = np.random.default_rng(0)
    halves = (steps[:, None] * scale * (np.arange(0, 60)[None, :] + 0.5)).astype(np.int64)
    values = np.unique(
        np.concatenate(
            [
                rng.integers(-(1 << 25) + 1, 1 << 25, 4000),
                (halves[:, :, None] + np.array([-1, 0, 1])).ravel(),
                [0, 1, -1, (1 << 25) - 1, -(1 << 25) + 1],
            ]
        )
    )
    values = values[np.abs(values) < 1 << 25]
    out = wp.zeros((len(values), len(steps)), dtype=int, device="cpu")
    wp.launch(
        _quantise_all,
        dim=out.shape,
        inputs=[
            wp.array(values, dtype=int, device="cpu"),
            wp.array(steps, dtype=int, device="cpu"),
            wp.array(warp_jpeg.reciprocals(steps), dtype=wp.int64, device="cpu"),
        ],
        outputs=[out],
        device="cpu",
    )
    step = steps[None, :] * scale
    expected = np.sign(values)[:, None] * ((np.abs(values)[:, None] + step // 2) // step)
    np.testing.assert_array_equal(out.numpy(), expected)
    with pytest.raises(ValueError, match="1-255"):
        warp_jpeg.reciprocals(np.array([0, 4]))
