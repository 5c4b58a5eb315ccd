"""Episode frames are written off the event loop by one thread (agent/records.py), without
weakening what the records promise: a result.json never exists before every frame of its
episode is on disk, a failed write is that episode's error, and nothing waits on the loop for
the disk."""

from __future__ import annotations

import threading

import pytest

from vabench.agent.records import EpisodeRecorder, EpisodeResult
from vabench.run_layout import EpisodeDir


def _result() -> EpisodeResult:
    return EpisodeResult(
        task="grasp_single_cube",
        seed=1,
        model="m",
        protocol="active",
        run=1,
        step_budget=5,
        n_checkpoints=1,
        status="success",
        success=True,
        stop_reason="success",
    )


def test_the_result_is_written_after_every_frame(tmp_path, monkeypatch):
    """The writer thread is held back: `finish` waits for it instead of writing a result that
    names frames not yet on disk."""
    import vabench.agent.records as records

    gate = threading.Event()
    real = records.Path.write_bytes

    def slow(path, data):
        gate.wait(5)
        return real(path, data)

    monkeypatch.setattr(records.Path, "write_bytes", slow)
    rec = EpisodeRecorder(tmp_path / "ep")
    paths = [rec.frame(step, bytes([step]) * 1000) for step in range(5)]
    assert not (tmp_path / "ep" / paths[-1]).exists()  # handed over, not yet written
    threading.Timer(0.2, gate.set).start()
    rec.finish(_result())
    assert EpisodeDir(tmp_path / "ep").result.exists()
    for step, rel in enumerate(paths):
        assert (tmp_path / "ep" / rel).read_bytes() == bytes([step]) * 1000


def test_a_failed_write_is_the_episodes_error(tmp_path):
    rec = EpisodeRecorder(tmp_path / "ep")
    frames = EpisodeDir(tmp_path / "ep").frames
    frames.rmdir()
    frames.write_text("not a directory")  # every frame write now fails
    rec.frame(0, b"jpeg")
    with pytest.raises(OSError):
        rec.finish(_result())
    assert not EpisodeDir(tmp_path / "ep").result.exists()
    rec.close()
