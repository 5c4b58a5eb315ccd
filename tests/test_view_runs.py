"""The viewer beyond one run page, over real HTTP on loopback, on synthetic runs
(benchmarks/synthetic_runs.py): hints only of the episode's own protocol; a directory of runs
(the run list, each run's own pages under it); every model's episode of one trial side by
side, across runs and within one."""

from __future__ import annotations

import asyncio
import re
import shutil
import sys
from html import unescape
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from vabench.view.__main__ import main, open_path
from vabench.view.app import Viewer
from vabench.view.runs import MAX_DEPTH, RunsViewer

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


@pytest.fixture
def runs(pristine, tmp_path):
    """runs/a (a run), runs/group/b (the same run, a level deeper), runs/broken (a ledger
    that is not one), runs/fresh (a plan, no episode finished yet), runs/.hidden (ignored)."""
    root = tmp_path / "runs"
    shutil.copytree(pristine.run_dir, root / "a")
    shutil.copytree(pristine.run_dir, root / "group" / "b")
    (root / "broken").mkdir()
    (root / "broken" / "plan.json").write_text("{}")
    (root / "broken" / "results.jsonl").write_text("not a record\n")
    (root / "fresh").mkdir()
    shutil.copy(pristine.run_dir / "plan.json", root / "fresh" / "plan.json")
    shutil.copytree(pristine.run_dir, root / ".hidden")
    return root


def test_a_directory_of_runs_lists_them_and_serves_each(runs, pristine):
    viewer = RunsViewer(runs)
    assert [e.name for e in viewer.entries] == ["a", "broken", "fresh", "group/b"]

    async def body(http):
        listing = await (await http.get("/")).text()
        inner = await (await http.get("/runs/3/api/run", params={"limit": 3})).json()
        page = await (await http.get("/runs/3/")).text()
        css = await http.get("/static/app.css")
        return listing, inner, page, css.status

    listing, inner, page, css = serve(viewer.app(), body)
    planned, done = pristine.planned, pristine.finished
    assert f"{done} / {planned}" in listing and "model-0, model-1" in listing
    assert "href='runs/0/'>a</a>" in listing and "href='runs/3/'>group/b</a>" in listing
    broken = next(r for r in listing.split("<tr") if ">broken<" in r)
    assert "class='error'" in broken  # listed with its problem
    fresh = next(r for r in listing.split("<tr") if ">fresh<" in r)
    assert f"0 / {planned}" in fresh and "no episode finished yet" in fresh  # not an error
    assert ".hidden" not in listing
    assert inner["name"] == "b" and inner["total"] == done and len(inner["episodes"]) == 3
    assert "run.js" in page and css == 200


def test_runs_dir_command_line(runs, tmp_path, capsys):
    """`python -m vabench.view runs/` used to answer `runs/results.jsonl: not found`."""
    assert isinstance(open_path(runs), RunsViewer)
    assert isinstance(open_path(runs / "a"), Viewer)
    (tmp_path / "empty").mkdir()
    assert main([str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert "no run directory" in err and f"within {MAX_DEPTH} levels" in err


def test_compare_one_trial_across_runs_and_within_one(runs):
    viewer = RunsViewer(runs)
    index = viewer.entries[0].viewer.index
    ref = next(r for r in index.episodes.values() if r.track == "passive")
    trial = {"task": ref.result.task, "seed": ref.result.seed, "track": "passive"}
    models = sorted(
        {
            r.result.model
            for r in index.episodes.values()
            if (r.result.task, r.result.seed, r.track)
            == (ref.result.task, ref.result.seed, "passive")
        }
    )

    async def body(http):
        r = await http.get("/compare", params=trial)
        page = await r.text()
        images = re.findall(r"src='([^']+)'", page)
        got = [(await http.get(unescape(src))).status for src in images]
        episodes = re.findall(r"href='(runs/\d/episode\?id=[^']+)'", page)
        opened = [(await http.get("/" + unescape(e))).status for e in episodes]
        bad = await http.get("/compare", params={**trial, "seed": "x"})
        within = await (await http.get("/runs/0/compare", params=trial)).text()
        return page, got, opened, (bad.status, await bad.text()), within

    page, got, opened, bad, within = serve(viewer.app(), body)
    rows = page.count("<tr><td>")
    assert rows == 2 * len(models)  # every model's episode, in both runs
    assert set(got) == {200} and len(got) == 2 * rows  # first and last image of each
    assert set(opened) == {200} and len(opened) == rows
    assert bad[0] == 400 and "seed: expected a whole number" in bad[1]
    assert within.count("<tr><td>") == len(models)
    for model in models:
        assert f"<td>{model}</td>" in within


def test_bundle_is_a_static_site_with_relative_links_only(run, tmp_path, capsys):
    out = tmp_path / "bundle"
    assert main([str(run), "--bundle", str(out)]) == 0
    n = len(Viewer(run).index.episodes)
    assert f"wrote {n} episodes" in capsys.readouterr().out
    pages = sorted(out.rglob("*.html"))
    assert (out / "index.html") in pages and len(list((out / "e").glob("*.html"))) == n
    images = 0
    for html in pages:
        for ref in re.findall(r"(?:href|src)='([^']*)'", html.read_text()):
            ref = unescape(ref)
            assert "://" not in ref and not ref.startswith("/"), (html, ref)
            target = (html.parent / ref).resolve()
            assert target.is_file() and target.is_relative_to(out.resolve()), (html, ref)
            images += ref.endswith(".jpg")
    assert images > n  # every episode shows what its model saw
    first = (out / "e" / "0.html").read_text()
    assert "EVALUATOR-ONLY" in first and "href='../index.html'" in first
    assert main([str(run), "--bundle", str(out)]) == 2  # never written over
    assert "--bundle: " in capsys.readouterr().err
