"""The viewer over real HTTP on loopback, on a real smoke run: the JSON endpoints, path
traversal refused, bad input answered with one message naming the field, cross-origin and
non-JSON posts refused, two viewers and many concurrent posts losing nothing."""

from __future__ import annotations

import asyncio
import os

import aiohttp
import pytest
from aiohttp import web
from diag_util import ACTIVE, PASSIVE, copy_run

from vabench.diagnostics.episodes import RunIndex
from vabench.diagnostics.store import AnnotationStore
from vabench.view.__main__ import main
from vabench.view.app import Viewer


@pytest.fixture
def run(tmp_path_factory, tmp_path):
    return copy_run(tmp_path_factory.getbasetemp(), tmp_path / "run")


class Served:
    def __init__(self, run_dir):
        self.viewer = Viewer(run_dir)
        self.runner = web.AppRunner(self.viewer.app(), access_log=None)

    async def __aenter__(self):
        await self.runner.setup()
        site = web.TCPSite(self.runner, "127.0.0.1", 0)
        await site.start()
        self.url = f"http://127.0.0.1:{self.runner.addresses[0][1]}"
        return self

    async def __aexit__(self, *exc):
        await self.runner.cleanup()


def serve(run_dir, body):
    async def go():
        async with Served(run_dir) as s, aiohttp.ClientSession(s.url) as http:
            return await body(s, http)

    return asyncio.run(go())


def test_run_episode_and_frames(run):
    async def body(s, http):
        r = await http.get("/api/run")
        listing = await r.json()
        assert listing["frames_kept"] == "all"  # the run's records.frames (its default)
        episodes = listing["episodes"]
        assert [e["id"] for e in episodes] == [ACTIVE, PASSIVE]
        assert {"success", "checkpoints_reached", "n_checkpoints"} <= set(episodes[0])
        r = await http.get("/api/episode", params={"id": PASSIVE})
        timeline = await r.json()
        assert timeline["frames_note"] is None
        assert len(timeline["steps"]) == 4
        step = timeline["steps"][0]
        assert (
            len(step["frames"]) == 5
            and step["replies"]
            and step["action"]["valid"] in (True, False)
        )
        assert set(step["evaluator"]) == {"checks", "objects", "progress", "success"}
        r = await http.get("/api/frame", params={"episode": PASSIVE, "file": step["frames"][0]})
        assert r.status == 200 and r.content_type == "image/jpeg"
        assert (await r.read())[:2] == b"\xff\xd8"
        r = await http.get("/")
        assert r.status == 200 and "script-src 'self'" in r.headers["Content-Security-Policy"]
        assert r.headers["X-Frame-Options"] == "DENY"

    serve(run, body)


def test_path_traversal_is_refused(run):
    frames = run / "episodes" / ACTIVE / "frames"
    os.symlink("/etc/hostname", frames / "evil.jpg")
    (run / "secret.jpg").write_bytes(b"\xff\xd8 not for you")

    async def body(s, http):
        for name in (
            "../../../../../../../../etc/passwd",
            "../result.json",
            "frames/../../../../../secret.jpg",
            "/etc/hostname",
            "frames/evil.jpg",
            "frames/%2e%2e/%2e%2e/x.jpg",
        ):
            r = await http.get("/api/frame", params={"episode": ACTIVE, "file": name})
            assert r.status in (403, 404), name
            assert (await r.json())["field"] == "file"
        for episode in ("../../../etc", "local/../../../etc/passwd", ""):
            r = await http.get("/api/episode", params={"id": episode})
            assert r.status == 404 and "unknown episode" in (await r.json())["error"]
        for raw in (
            "/static/../app.py",
            "/static/%2e%2e/app.py",
            "/static/..%2fapp.py",
            "/static/%2e%2e%2f%2e%2e%2fdiagnostics%2fstore.py",
        ):
            r = await http.get(aiohttp.client.URL(raw, encoded=True))
            assert r.status in (403, 404), raw
        r = await http.get("/static/common.js")
        assert r.status == 200

    serve(run, body)


def test_bad_posts_get_one_clear_message(run):
    async def body(s, http):
        async def post(data, **kw):
            r = await http.post("/api/judgment", json=data, **kw)
            return r.status, await r.json()

        good = {"annotator": "alice", "episode": ACTIVE, "item": "TL", "value": 1}
        assert (await post(good))[0] == 200
        cases = [
            ({**good, "annotator": "<img src=x onerror=alert(1)>"}, 400, "annotator"),
            ({**good, "episode": "nope"}, 404, "episode"),
            ({**good, "item": "ZZ"}, 400, "item"),
            ({**good, "item": "ED"}, 400, "item"),  # not activated: no error gate yet
            ({**good, "value": "yes"}, 400, "value"),
            ({**good, "extra": 1}, 400, "extra"),
            ({"annotator": "alice", "episode": ACTIVE, "item": "TL"}, 400, "value"),
        ]
        for data, status, field in cases:
            got, answer = await post(data)
            assert (got, answer["field"]) == (status, field), data
            assert field in answer["error"] or "unknown episode" in answer["error"]
        r = await http.post(
            "/api/judgment",
            data="annotator=alice",
            headers={"Content-Type": "application/x-www-form-urlencoded"},
        )
        assert r.status == 415
        r = await http.post("/api/judgment", json=good, headers={"Origin": "http://evil.test"})
        assert r.status == 403 and (await r.json())["field"] == "origin"
        r = await http.post("/api/judgment", data="{", headers={"Content-Type": "application/json"})
        assert r.status == 400 and (await r.json())["field"] == "body"
        r = await http.get("/api/annotations", params={"episode": ACTIVE, "annotator": "a b"})
        assert r.status == 400 and (await r.json())["field"] == "annotator"

    serve(run, body)
    lines = (run / "annotations" / "alice.jsonl").read_text().splitlines()
    assert len(lines) == 1


def test_two_viewers_and_concurrent_posts_lose_nothing(run):
    items = ["gate_error", "gate_ambiguity", "TL", "SR", "MS", "MP", "FG"]

    async def go():
        async with (
            Served(run) as a,
            Served(run) as b,
            aiohttp.ClientSession(a.url) as ha,
            aiohttp.ClientSession(b.url) as hb,
        ):
            posts = []
            for i in range(10):
                for who, http in (("alice", ha), ("alice", hb), ("bob", hb)):
                    for episode in (ACTIVE, PASSIVE):
                        for item in items:
                            data = {
                                "annotator": who,
                                "episode": episode,
                                "item": item,
                                "value": (i + len(item)) % 2,
                            }
                            posts.append(http.post("/api/judgment", json=data))
            answers = await asyncio.gather(*posts)
            assert {r.status for r in answers} == {200}
            r = await ha.get("/api/annotations", params={"episode": ACTIVE, "annotator": "bob"})
            return await r.json()

    state = asyncio.run(go())
    assert set(state["own"]) == set(items) and state["gates"]["gate_error"]["votes"] == 2
    store = AnnotationStore(RunIndex.load(run))
    loaded = store.load()
    assert loaded.problems == []
    assert len(loaded.judgments) == 10 * 3 * 2 * len(items)
    assert len(store.path("alice").read_text().splitlines()) == 10 * 2 * 2 * len(items)


def test_diagnostics_page_escapes_and_command_line(run, tmp_path, capsys):
    run = run.rename(tmp_path / "run<img src=x onerror=alert(1)>")  # names reach the page as text
    AnnotationStore(RunIndex.load(run)).record("alice", ACTIVE, "TL", 1)

    async def body(s, http):
        r = await http.get("/diagnostics")
        return await r.text()

    page = serve(run, body)
    assert "Inter-annotator agreement" in page and "annotators: alice" in page
    assert "<img" not in page and "run&lt;img src=x onerror=alert(1)&gt;" in page
    assert main([str(tmp_path / "nowhere")]) == 2
    assert "nowhere: no such directory" in capsys.readouterr().err
