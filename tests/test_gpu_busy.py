"""The GPU busy share a sweep's host lines and a Ray engine's report give (vabench/sweep/
gpu_busy.py). There is no NVIDIA driver here: an executable `nvidia-smi` on PATH answers the
query the way the driver's tool does (its CSV, GPUs by index and UUID), each call a real
process, so the sampler's command, parsing, GPU selection and sums are what is tested."""

from __future__ import annotations

import logging
import os
import stat
import threading
import time
from pathlib import Path

import pytest

from vabench.tuning import gpu_busy, hostload
from vabench.tuning.gpu_busy import GpuBusy, Totals, parse
from vabench.tuning.hostload import HostLoad

LISTING = (
    "0, GPU-aaaa1111-0000-0000-0000-000000000000, 10, 1000\n"
    "1, GPU-bbbb2222-0000-0000-0000-000000000000, 70, 20000\n"
    "2, GPU-cccc3333-0000-0000-0000-000000000000, 40, 3000\n"
)


def fake_smi(folder: Path, body: str) -> Path:
    """An `nvidia-smi` in `folder` that checks it was asked the sampler's query and prints
    `body` (a shell snippet's output)."""
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / "nvidia-smi"
    path.write_text(
        "#!/bin/sh\n"
        f'[ "$1" = "--query-gpu={gpu_busy.QUERY}" ] || {{ echo "bad query $1" >&2; exit 6; }}\n'
        + body
    )
    path.chmod(path.stat().st_mode | stat.S_IEXEC)
    return path


def counting_smi(tmp_path: Path, body: str) -> Path:
    """A `fake_smi` whose `body` may read `$n`: 1 on its first call, 2 on the next, ..."""
    count = tmp_path / "n"
    count.write_text("0")
    return fake_smi(tmp_path / "bin", f"n=$(( $(cat {count}) + 1 )); echo $n > {count}\n" + body)


def wait_for_readings(sampler: GpuBusy, n: int) -> Totals:
    """The sampler's sums once it has taken `n` readings (30 s at most)."""
    deadline = time.monotonic() + 30
    while sampler.totals().readings < n and time.monotonic() < deadline:
        time.sleep(0.01)
    return sampler.totals()


@pytest.mark.parametrize(
    "watched, busy, memory",
    [
        ((), (0.10 + 0.70 + 0.40) / 3, 24000.0),  # every GPU listed
        (("1",), 0.70, 20000.0),
        (("GPU-cccc3333",), 0.40, 3000.0),  # a UUID prefix, as CUDA_VISIBLE_DEVICES may give
        (("0", "2"), 0.25, 4000.0),
    ],
)
def test_a_reading_is_of_the_gpus_the_process_sees(watched, busy, memory):
    reading = parse(LISTING, watched)
    assert reading is not None
    assert reading.busy == pytest.approx(busy)
    assert reading.memory_mib == memory


def test_a_gpu_not_listed_or_a_figure_not_a_number_reads_nothing():
    assert parse(LISTING, ("7",)) is None
    assert parse("0, GPU-aaaa, [N/A], 1000\n", ()) is None
    assert parse("", ()) is None


def test_the_sampler_sums_its_readings_and_gives_the_mean_between_two(tmp_path):
    # the busy share climbs 20, 40, 60, ... % call after call
    smi = counting_smi(
        tmp_path,
        'echo "0, GPU-aaaa, 5, 100"\n'
        'echo "1, GPU-bbbb, $(( n * 20 > 100 ? 100 : n * 20 )), $(( n * 1000 ))"\n',
    )
    sampler = GpuBusy(every_s=0.05, environ={"CUDA_VISIBLE_DEVICES": "1"}, command=str(smi))
    with sampler:
        first = wait_for_readings(sampler, 2)
        later = wait_for_readings(sampler, first.readings + 2)
    assert sampler.failed is None
    n0, n1 = first.readings, later.readings
    assert n1 >= n0 + 2
    # readings k = 1..n: min(20 k, 100) % of GPU 1 only (GPU 0's 5 % never counted)
    expected = [min(20 * k, 100) / 100 for k in range(1, n1 + 1)]
    assert later.mean_since() == pytest.approx(sum(expected) / n1)
    assert later.mean_since(first) == pytest.approx(sum(expected[n0:]) / (n1 - n0))
    assert later.memory_max_mib == 1000 * n1
    assert Totals().mean_since() is None


def test_a_missing_or_failing_tool_is_said_once_and_reads_nothing(tmp_path, caplog):
    failing = fake_smi(tmp_path / "bin", 'echo "driver not loaded" >&2; exit 9\n')
    for command, why in [
        (str(failing), "exited 9: driver not loaded"),
        (str(tmp_path / "none"), "No such file"),
    ]:
        sampler = GpuBusy(every_s=0.01, environ={"CUDA_VISIBLE_DEVICES": "0"}, command=command)
        with caplog.at_level(logging.INFO, logger="vabench.tuning.gpu_busy"), sampler:
            sampler._thread.join(timeout=30)  # it ends by itself after the failure
        assert not sampler._thread.is_alive()
        assert sampler.totals().readings == 0
        assert why in (sampler.failed or "")
        lines = [r.getMessage() for r in caplog.records if "not sampled" in r.getMessage()]
        assert len(lines) == 1 and why in lines[0]
        caplog.clear()


def test_one_sampler_serves_the_process_and_the_last_user_stops_it(tmp_path, monkeypatch):
    calls = tmp_path / "calls"
    smi = fake_smi(tmp_path / "bin", f'echo x >> {calls}\necho "0, GPU-aaaa, 50, 100"\n')
    monkeypatch.setenv("PATH", f"{smi.parent}{os.pathsep}{os.environ['PATH']}")
    with gpu_busy.sampling({"CUDA_VISIBLE_DEVICES": "0"}) as a:
        with gpu_busy.sampling({"CUDA_VISIBLE_DEVICES": "0"}) as b:
            assert a is b is not None
        assert a._thread is not None and a._thread.is_alive()  # one user left
    assert a._thread is not None
    a._thread.join(timeout=15)
    assert not a._thread.is_alive()
    assert [t for t in threading.enumerate() if t.name == "gpu-busy"] == []
    # no GPU visible: no sampler, the tool never asked
    before = calls.read_text() if calls.exists() else ""
    with gpu_busy.sampling({"CUDA_VISIBLE_DEVICES": ""}) as none:
        assert none is None
    assert (calls.read_text() if calls.exists() else "") == before


def test_the_host_line_says_how_busy_the_gpu_was(tmp_path):
    smi = fake_smi(tmp_path / "bin", 'echo "0, GPU-aaaa, 70, 2048"\n')
    sampler = GpuBusy(every_s=0.02, environ={"CUDA_VISIBLE_DEVICES": "0"}, command=str(smi))
    with sampler:
        load = HostLoad(every_s=1.0, gpus=sampler)
        load.tick()
        wait_for_readings(sampler, sampler.totals().readings + 2)
        w = load.tick()
    assert w is not None and w.gpu_busy == pytest.approx(0.70)
    assert "GPU busy 70% (memory 2.0 GiB at most)" in w.describe()
    whole = load.whole_run()
    assert whole is not None and whole.gpu_busy == pytest.approx(0.70)
    # without a sampler the line says nothing of a GPU
    plain = HostLoad(every_s=1.0)
    plain.tick()
    time.sleep(0.05)
    w = plain.tick()
    assert w is not None and w.gpu_busy is None and "GPU" not in w.describe()
    assert hostload.Window(1.0, {}, 0.0, 0.0).gpu_busy is None


def test_one_failed_reading_is_not_the_end_and_n_a_is_said_as_such(tmp_path, caplog):
    # the first call fails (a slow or busy driver), the next ones answer
    smi = counting_smi(
        tmp_path,
        '[ $n -eq 1 ] && { echo "timed out" >&2; exit 15; }\necho "0, GPU-aaaa, 30, 100"\n',
    )
    sampler = GpuBusy(every_s=0.02, environ={"CUDA_VISIBLE_DEVICES": "0"}, command=str(smi))
    with sampler:
        wait_for_readings(sampler, 2)
    assert sampler.totals().readings >= 2
    assert sampler.totals().mean_since() == pytest.approx(0.30)
    # a GPU that reports no utilisation: said as such, and given up after MAX_FAILURES
    na = fake_smi(tmp_path / "na", 'echo "0, GPU-aaaa, [N/A], 100"\n')
    sampler = GpuBusy(every_s=0.01, environ={"CUDA_VISIBLE_DEVICES": "0"}, command=str(na))
    with caplog.at_level(logging.INFO, logger="vabench.tuning.gpu_busy"), sampler:
        sampler._thread.join(timeout=30)
    assert not sampler._thread.is_alive() and sampler.totals().readings == 0
    assert "no utilisation ([N/A])" in (sampler.failed or "")
    assert len([r for r in caplog.records if "not sampled" in r.getMessage()]) == 1


def test_mig_instances_alone_are_not_sampled_as_the_whole_node(tmp_path):
    smi = fake_smi(tmp_path / "bin", f'echo "{LISTING}"\n')
    mig = {"CUDA_VISIBLE_DEVICES": "MIG-11111111-2222-3333-4444-555555555555"}
    sampler = GpuBusy(every_s=0.01, environ=mig, command=str(smi))
    assert sampler.read() is None and "MIG" in (sampler.failed or "")
    with gpu_busy.sampling(mig) as none:
        assert none is None
