"""The viewer's run page at scale, on a synthetic run (benchmarks/synthetic_runs.py): pages and
filters cover every episode once, in the index's order; the n/p neighbours walk the filtered
order; a ledger that grows is read from where it was left (a line being written waits), and
anything else reloads it from the start; the annotation panel sees only its episode's votes."""

from __future__ import annotations

import asyncio
import json
import shutil
import sys
from pathlib import Path

import aiohttp
import pytest
from aiohttp import web

from vabench.diagnostics.episodes import RunDirError, RunIndex
from vabench.run_layout import RunDir
from vabench.view.app import Viewer
from vabench.view.listing import Listing, LiveIndex

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from synthetic_runs import make_run


@pytest.fixture(scope="module")
def pristine(tmp_path_factory):
    return make_run(tmp_path_factory.mktemp("synthetic"), 120, annotated=0.1)


@pytest.fixture
def run(pristine, tmp_path):
    return Path(shutil.copytree(pristine.run_dir, tmp_path / "run"))


def serve(viewer: Viewer, body):
    async def go():
        runner = web.AppRunner(viewer.app(), access_log=None)
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


def ledger_lines(run: Path) -> list[dict]:
    return [json.loads(x) for x in RunDir(run).results.read_text().splitlines()]


def another_run(line: dict, run_no: int) -> dict:
    """The line of the same episode in a run the plan does not have (a new episode id)."""
    rel = line["episode_dir"].rsplit("/run_", 1)[0] + f"/run_{run_no}"
    return {**line, "run": run_no, "episode_dir": rel}


def test_pages_and_filters_cover_every_episode_once(run):
    viewer = Viewer(run)
    order = list(viewer.index.episodes)

    async def body(http):
        seen, offset = [], 0
        while True:
            page = await (await http.get("/api/run", params={"offset": offset, "limit": 7})).json()
            assert page["total"] == page["matched"] == len(order)
            if not page["episodes"]:
                break
            seen += [e["id"] for e in page["episodes"]]
            offset += 7
        assert seen == order
        page = await (await http.get("/api/run", params={"track": "passive"})).json()
        passive = [e["id"] for e in page["episodes"]]
        assert passive == [i for i in order if i.split("/")[1] == "passive"]
        assert page["matched"] == len(passive) < page["total"]
        assert set(page["facets"]["track"]) == {"active", "passive", "transfer", "long_horizon"}
        page = await (await http.get("/api/run", params={"outcome": "unscored"})).json()
        assert all(not e["scored"] for e in page["episodes"])
        for params, field in (({"limit": 0}, "limit"), ({"offset": "x"}, "offset")):
            r = await http.get("/api/run", params=params)
            assert r.status == 400 and (await r.json())["field"] == field
        annotated = await (await http.get("/api/run", params={"limit": 5000})).json()
        return {e["id"]: e["annotators"] for e in annotated["episodes"] if e["annotators"]}

    annotators = serve(viewer, body)
    assert annotators and all(a == ["alice", "bob", "judge-a"] for a in annotators.values())


def test_neighbours_walk_the_filtered_order(run):
    viewer = Viewer(run)
    wanted = [i for i in viewer.index.episodes if i.split("/")[1] == "active"]

    async def body(http):
        walked, at = [], wanted[0]
        while at is not None:
            walked.append(at)
            r = await http.get("/api/neighbours", params={"id": at, "track": "active"})
            step = await r.json()
            assert step["previous"] == (walked[-2] if len(walked) > 1 else None)
            at = step["next"]
        r = await http.get("/api/neighbours", params={"id": "nope"})
        assert r.status == 404
        return walked

    assert serve(viewer, body) == wanted


def test_a_growing_ledger_is_read_from_where_it_was_left(run):
    live = LiveIndex(run)
    listing = Listing(live)
    before = list(live.index.episodes)
    lines = ledger_lines(run)
    scored = [x for x in lines if x["status"] in ("success", "failure")]
    new = [another_run(x, 7) for x in scored[:3]]
    results = RunDir(run).results
    with results.open("a") as f:
        f.write("".join(json.dumps(x) + "\n" for x in new))
        cut = json.dumps(another_run(scored[3], 7))
        f.write(cut[:40])  # a line being written
    assert live.refresh() and live.reloads == 1
    ids = list(live.index.episodes)
    assert len(ids) == len(before) + 3 and set(before) < set(ids)
    assert ids == list(RunIndex.load(run).episodes)  # in order, as read from the start
    assert listing.page({}, 0, 5000)["total"] == len(ids)
    assert not live.refresh()  # nothing more came
    with results.open("a") as f:
        f.write(cut[40:] + "\n")
    assert live.refresh() and live.reloads == 1 and len(live.index.episodes) == len(ids) + 1
    # a line for an episode it holds: read again from the start, as the report would
    with results.open("a") as f:
        f.write(json.dumps(new[0]) + "\n")
    with pytest.raises(RunDirError, match="duplicate scored record"):
        live.refresh()  # two scored records of one episode: the ledger's reader refuses them
    results.write_text("".join(json.dumps(x) + "\n" for x in lines[:-2]))  # cut: from the start
    assert live.refresh() and live.reloads == 2
    assert len(live.index.episodes) == len(before) - 2


def test_the_viewer_keeps_its_annotations_as_the_ledger_grows(run):
    viewer = Viewer(run)
    episode = next(e for e, ref in viewer.index.episodes.items() if ref.result.scored)
    viewer.store.record("carol", episode, "TL", 1)
    line = another_run(ledger_lines(run)[0], 8)
    with RunDir(run).results.open("a") as f:
        f.write(json.dumps(line) + "\n")

    async def body(http):
        page = await (await http.get("/api/run", params={"limit": 5000})).json()
        state = await http.get("/api/annotations", params={"episode": episode, "annotator": "x"})
        return page, await state.json()

    page, state = serve(viewer, body)
    assert viewer.live.reloads == 1 and page["total"] == len(viewer.index.episodes)
    assert "carol" in next(e["annotators"] for e in page["episodes"] if e["id"] == episode)
    assert line["episode_dir"].removeprefix("episodes/") in viewer.index.episodes
    assert state["own"] == {} and set(state["gates"]) == {"gate_error", "gate_ambiguity"}
