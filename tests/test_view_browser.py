"""The viewer in a real browser: Debian's chromium, headless, driven by Playwright, against
`python -m vabench.view` serving a run made by the smoke config. Open the run, filter, open an
episode, step through it with the keyboard, annotate it in two stages, reload and find the
annotation kept, go to the next episode, and check the annotator's JSONL file.

Set VABENCH_SCREENSHOTS=DIR to also save the timeline and the diagnostics page as PNGs.
"""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest
from diag_util import ACTIVE, PASSIVE, REPO, copy_run

CHROMIUM = "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
]

if not Path(CHROMIUM).exists() and not os.environ.get("CI"):
    pytest.skip(
        f"the viewer's browser test needs Debian's chromium at {CHROMIUM} "
        "(apt-get install chromium; .ci/run installs it)",
        allow_module_level=True,
    )
sync_api = pytest.importorskip("playwright.sync_api")


def launch(path):
    """`python -m vabench.view PATH --port 0`: (process, its URL)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "vabench.view", str(path), "--port", "0"],
        cwd=REPO,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    line = proc.stdout.readline()
    found = re.search(r"at (http://127\.0\.0\.1:\d+)/", line)
    assert found, line
    return proc, found.group(1)


@pytest.fixture
def viewer(tmp_path_factory, tmp_path):
    run = copy_run(tmp_path_factory.getbasetemp(), tmp_path / "run")
    proc, url = launch(run)
    yield run, url
    proc.terminate()
    proc.wait(timeout=20)


@pytest.fixture
def runs_viewer(tmp_path_factory, tmp_path):
    """A directory of two runs, runs/first and runs/later/second."""
    base = tmp_path_factory.getbasetemp()
    copy_run(base, tmp_path / "runs" / "first")
    copy_run(base, tmp_path / "runs" / "later" / "second")
    proc, url = launch(tmp_path / "runs")
    yield url
    proc.terminate()
    proc.wait(timeout=20)


@pytest.fixture
def page():
    with sync_api.sync_playwright() as p:
        browser = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        page = browser.new_page(viewport={"width": 1400, "height": 900})
        errors: list[str] = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        yield page
        browser.close()
        assert errors == []


def ready(page):
    page.wait_for_selector("body[data-ready='1']", timeout=30_000)


def vote(page, item, value):
    page.click(f"button[data-item='{item}'][data-value='{value}']")
    page.wait_for_selector(f"#status:has-text('saved {item} = {value}')")


def chosen(page, item):
    return page.get_attribute(f"button.vote.chosen[data-item='{item}']", "data-value")


def test_annotate_an_episode_in_the_browser(viewer, page):
    run, url = viewer
    page.goto(url + "/")
    ready(page)
    assert page.locator("#episodes tbody tr").count() == 2
    page.select_option("#f-track", "passive")  # the server filters: wait for its page
    ready(page)
    assert page.locator("#episodes tbody tr").count() == 1
    page.select_option("#f-track", "")
    ready(page)
    page.fill("#annotator", "alice")
    page.dispatch_event("#annotator", "change")
    page.click(f"#episodes tbody tr[data-id='{ACTIVE}'] a")
    ready(page)
    assert page.inner_text("#title") == ACTIVE
    assert page.locator("#steps .step").count() == 4
    loaded = page.evaluate(
        "[...document.querySelectorAll('img.frame')].map(i => i.complete && i.naturalWidth > 0)"
    )
    assert loaded == [True] * 4
    assert page.locator("details.evaluator summary").first.inner_text().startswith("EVALUATOR-ONLY")

    # keyboard navigation between steps
    assert page.get_attribute("body", "data-step") == "1"
    page.keyboard.press("ArrowRight")
    page.keyboard.press("j")
    assert page.get_attribute("body", "data-step") == "3"
    page.keyboard.press("ArrowLeft")
    assert page.get_attribute("body", "data-step") == "2"

    # stage one, then the criteria the gates activate
    assert page.is_disabled("button[data-item='ED'][data-value='1']")
    vote(page, "gate_error", 1)
    vote(page, "gate_ambiguity", 0)
    assert page.is_enabled("button[data-item='ED'][data-value='1']")
    assert page.is_disabled("button[data-item='AE'][data-value='1']")
    for item, value in (
        ("TL", 1),
        ("SR", 0),
        ("MS", 1),
        ("MP", 0),
        ("FG", 0),
        ("ED", 1),
        ("OC", 0),
        ("PF", 1),
    ):
        vote(page, item, value)
    if os.environ.get("VABENCH_SCREENSHOTS"):
        page.screenshot(path=str(Path(os.environ["VABENCH_SCREENSHOTS"]) / "timeline.png"))

    page.reload()
    ready(page)
    assert chosen(page, "gate_error") == "1" and chosen(page, "gate_ambiguity") == "0"
    assert (chosen(page, "TL"), chosen(page, "SR"), chosen(page, "ED")) == ("1", "0", "1")
    assert chosen(page, "AE") == "null"  # nothing recorded: not activated

    page.keyboard.press("n")  # the next episode of the run page's order
    page.wait_for_url(re.compile(r"passive"))
    ready(page)
    assert page.inner_text("#title") == PASSIVE
    assert page.locator("img.frame").count() == 4 * 5  # the five-view bundle of every step

    lines = [json.loads(x) for x in (run / "annotations" / "alice.jsonl").open()]
    assert {(x["episode"], x["item"], x["value"]) for x in lines} == {
        (ACTIVE, "gate_error", 1),
        (ACTIVE, "gate_ambiguity", 0),
        (ACTIVE, "TL", 1),
        (ACTIVE, "SR", 0),
        (ACTIVE, "MS", 1),
        (ACTIVE, "MP", 0),
        (ACTIVE, "FG", 0),
        (ACTIVE, "ED", 1),
        (ACTIVE, "OC", 0),
        (ACTIVE, "PF", 1),
    }
    assert {x["annotator"] for x in lines} == {"alice"} and len(lines) == 10

    page.goto(url + "/diagnostics")
    assert "Inter-annotator agreement" in page.inner_text("body")
    if os.environ.get("VABENCH_SCREENSHOTS"):
        page.screenshot(
            path=str(Path(os.environ["VABENCH_SCREENSHOTS"]) / "agreement.png"), full_page=True
        )


def test_a_directory_of_runs_in_the_browser(runs_viewer, page):
    url = runs_viewer
    page.goto(url + "/")
    ready(page)
    rows = page.locator("table.runs tbody tr")
    names = [rows.nth(i).locator("td").first.inner_text() for i in range(rows.count())]
    assert names == ["first", "later/second"]
    assert "2 / 2" in rows.nth(1).inner_text()  # episodes done / planned
    page.click("text=later/second")
    ready(page)  # the run's own page, under /runs/1/
    assert page.inner_text("#title") == "run second"
    assert page.locator("#episodes tbody tr").count() == 2
    page.click(f"#episodes tbody tr[data-id='{ACTIVE}'] td:last-child a")  # compare, this run
    assert page.locator("table.compare tr:has(td)").count() == 1
    page.goto(url + "/compare?task=grasp_single_cube&seed=1000&track=active")  # both runs
    assert page.locator("table.compare tr:has(td)").count() == 2
    loaded = page.evaluate(
        "[...document.querySelectorAll('img.thumb')].map(i => i.complete && i.naturalWidth > 0)"
    )
    assert loaded == [True] * 4
    page.click("table.compare tr:has(td) >> nth=1 >> a")
    ready(page)
    assert page.inner_text("#title") == ACTIVE


def test_a_bundle_opens_from_disk(tmp_path_factory, tmp_path, page):
    run = copy_run(tmp_path_factory.getbasetemp(), tmp_path / "run")
    out = tmp_path / "bundle"
    subprocess.run(
        [sys.executable, "-m", "vabench.view", str(run), "--bundle", str(out)],
        cwd=REPO,
        check=True,
        timeout=120,
    )
    page.goto((out / "index.html").as_uri())
    assert page.locator("table.episodes tbody tr").count() == 2
    page.click(f"text={PASSIVE}")
    assert page.url.startswith("file://") and page.inner_text("h1") == PASSIVE
    loaded = page.evaluate(
        "[...document.querySelectorAll('img.thumb')].map(i => i.complete && i.naturalWidth > 0)"
    )
    assert loaded == [True] * 4 * 5  # the five-view bundle of every step
    page.click("text=run")
    assert page.url.endswith("/index.html")
