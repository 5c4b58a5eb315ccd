"""The kernel profile's stages and report (the recording itself needs CUPTI on a GPU host:
`benchmarks/gpu/run.sh main` with MAIN_KERNELS=1)."""

from __future__ import annotations

import json
import os
import re

from vabench.tuning import kernel_profile as kp


def test_kernels_are_put_in_their_stage_and_summed():
    assert kp.stage_of("_place_cameras_3f2a_cuda_kernel_forward") == "render"
    assert kp.stage_of("_compute_bvh_bounds_cuda_kernel_forward") == "render"
    assert kp.stage_of("_solver_iteration_9ab_cuda_kernel_forward") == "physics"
    assert kp.stage_of("Memcpy HtoD (Pinned -> Device)") == "copies"
    assert kp.stage_of("void nvjpeg::encode_huffman<int>(...)") == "jpeg"
    assert kp.stage_of("some_library_kernel") == "other"
    out = kp.summarize(
        {
            "_solver_cuda_kernel_forward": (10, 3_000_000.0),
            "render_megakernel_cuda_kernel_forward": (5, 1_000_000.0),
            "Memcpy DtoH": (2, 500_000.0),
        },
        window_s=10.0,
    )
    assert out["gpu_s"] == 4.5
    assert out["stages_s"] == {"physics": 3.0, "render": 1.0, "copies": 0.5}
    assert list(out["kernels"]) == [
        "_solver_cuda_kernel_forward",
        "render_megakernel_cuda_kernel_forward",
        "Memcpy DtoH",
    ]


def test_the_report_sums_every_process_and_names_a_failed_one(tmp_path):
    for pid, us in ((1, 2_000_000.0), (2, 6_000_000.0)):
        data = kp.summarize({"_solver_cuda_kernel_forward": (4, us)}, window_s=20.0)
        (tmp_path / f"kernels_{pid}.json").write_text(json.dumps(data))
    (tmp_path / "kernels_3.json").write_text(json.dumps({"error": "ModuleNotFoundError: torch"}))
    text = kp.report(tmp_path.glob("kernels_*.json"))
    assert "kernels_1.json: 2.00 s of kernels in 20 s (10% of the GPU's time" in text
    assert "kernels_3.json: ModuleNotFoundError: torch" in text
    assert "all: physics 8.00 s (100%)" in text
    assert "8 calls" in text


def test_a_window_is_recorded_only_where_asked_and_always_leaves_its_file(tmp_path):
    assert kp.record_in_background({}) is None
    env = {kp.FOLDER_VARIABLE: str(tmp_path), kp.AT_VARIABLE: "0", kp.SECONDS_VARIABLE: "0.01"}
    thread = kp.record_in_background(env)
    assert thread is not None
    thread.join(timeout=60)
    (path,) = tmp_path.glob("kernels_*.json")
    data = json.loads(path.read_text())
    assert data["at_s"] == 0.0 and data["pid"] == os.getpid()
    if "error" in data:  # no PyTorch or no CUPTI here: the reason, named
        assert re.match(r"\w+(Error|Exception)\b", data["error"]), data["error"]
    else:
        assert set(data) >= {"window_s", "gpu_s", "stages_s", "kernels"}


def test_the_renderers_own_jpeg_kernels_are_jpeg_not_physics():
    """Warp names a kernel's CUDA function by its Python name and its module's hash: the JPEG
    kernels' short names (`_pack`, `_place`) must not be read as MuJoCo Warp's physics, and
    `_place_cameras` (the render pass's) must stay render."""
    assert kp.stage_of("_pack_040c6695_cuda_kernel_forward") == "jpeg"
    assert kp.stage_of("_count_bits_a4d99693_cuda_kernel_forward") == "jpeg"
    assert kp.stage_of("_place_9f2fcb05_cuda_kernel_forward") == "jpeg"
    assert kp.stage_of("_kernels__locals__scan_b230974d_cuda_kernel_forward") == "jpeg"
    assert kp.stage_of("_place_cameras_3f2a1b2c_cuda_kernel_forward") == "render"
    assert kp.stage_of("_pack_rows_040c6695_cuda_kernel_forward") == "physics"


def test_every_kernel_of_the_jpeg_modules_is_listed():
    import warp as wp

    from vabench.render import warp_jpeg, warp_scan

    names = set()
    for module in (warp_jpeg, warp_scan):
        for value in vars(module).values():
            if isinstance(value, wp.Kernel):
                names.add(value.key)
    names.update(k.key for k in warp_scan._kernels(wp.int32))  # the CUDA names' prefixes
    assert names <= set(kp.WARP_JPEG_KERNELS), names - set(kp.WARP_JPEG_KERNELS)
