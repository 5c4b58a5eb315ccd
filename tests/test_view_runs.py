"""The viewer beyond one run page, over real HTTP on loopback, on synthetic runs
(benchmarks/synthetic_runs.py): hints only of the episode's own protocol."""

from __future__ import annotations

import asyncio
import shutil
import sys
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from vabench.view.app import Viewer

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from synthetic_runs import make_run

NO_CAMERA = "no camera action in the whole episode"


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("synthetic"), 1, runs=1, models=2)


@pytest.fixture
def run(pristine, tmp_path):
    return Path(shutil.copytree(pristine.run_dir, tmp_path / "run"))


def serve(app: web.Application, body):
    async def go():
        runner = web.AppRunner(app, access_log=None)
        await runner.setup()
        site = web.TCPSite(runner, "127.0.0.1", 0)
        await site.start()
        url = f"http://127.0.0.1:{runner.addresses[0][1]}"
        try:
            async with aiohttp.ClientSession(url) as http:
                return await body(http)
        finally:
            await runner.cleanup()

    return asyncio.run(go())


def test_camera_hints_only_on_episodes_that_can_move_the_camera(run):
    """The template episodes hold no camera action in either protocol: the active one gets
    the hint, the passive one (five fixed views, no camera actions) does not."""
    viewer = Viewer(run)
    ids = {
        p: next(i for i in viewer.index.episodes if i.split("/")[1] == p)
        for p in ("active", "passive")
    }

    async def body(http):
        got = {}
        for protocol, episode in ids.items():
            timeline = await (await http.get("/api/episode", params={"id": episode})).json()
            assert timeline["summary"]["protocol"] == protocol
            got[protocol] = [(h["item"], h["text"]) for h in timeline["hints"]]
        return got

    got = serve(viewer.app(), body)
    assert ("AE", NO_CAMERA) in got["active"]
    assert not [h for h in got["passive"] if h[0] == "AE"]
