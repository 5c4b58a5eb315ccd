"use strict";

// The server filters and pages the episodes (a run may hold 200,000): this page asks for one
// page of those passing the filters and shows how many pass.
const FILTERS = ["model", "track", "task", "outcome"];
const PAGE_SIZE = 500;
let OFFSET = 0;
let LOADING = 0;

const FRAMES_KEPT = { all: "every episode's", failed: "the failed episodes' only", none: "none" };

function fillSelect(name, values) {
  const select = document.getElementById("f-" + name);
  const keep = select.value;
  select.replaceChildren(el("option", { value: "" }, "all"),
    ...values.map((v) => el("option", { value: v }, v)));
  select.value = values.includes(keep) ? keep : "";
}

function outcomeOf(e) {
  return e.scored ? (e.success ? "success" : "failure") : "unscored";
}

function chosen() {
  const query = new URLSearchParams();
  for (const name of FILTERS) {
    const value = document.getElementById("f-" + name).value;
    if (value) query.set(name, value);
  }
  return query;
}

function render(run) {
  const body = document.querySelector("#episodes tbody");
  body.replaceChildren(...run.episodes.map((e) => el("tr", { "data-id": e.id, class: outcomeOf(e) },
    el("td", {}, el("a", { href: episodeUrl(e.id) }, e.id)),
    el("td", {}, e.model), el("td", {}, e.track), el("td", {}, e.task),
    el("td", {}, e.seed), el("td", {}, e.run),
    el("td", { class: "outcome" }, e.scored ? (e.success ? "✓ success" : "✗ failure") : e.status),
    el("td", {}, e.stop_reason), el("td", {}, `${e.steps_used}/${e.step_budget}`),
    el("td", {}, checkpointsText(e)),
    el("td", {}, e.annotators.join(", ")),
    el("td", {}, el("a", { href: "compare?" + new URLSearchParams(
      { task: e.task, seed: e.seed, track: e.track }) }, "models")))));
  const first = run.episodes.length ? run.offset + 1 : 0;
  const last = run.offset + run.episodes.length;
  document.getElementById("count").textContent =
    `${first}–${last} of ${run.matched} episodes` +
    (run.matched !== run.total ? ` (${run.total} in the run)` : "");
  document.getElementById("prev-page").disabled = run.offset <= 0;
  document.getElementById("next-page").disabled = last >= run.matched;
}

async function load() {
  const mine = ++LOADING;
  document.body.dataset.ready = "0";
  const query = chosen();
  // The episode page's n/p keys walk this filtered order.
  sessionStorage.setItem(ORDER_KEY, query.toString());
  query.set("offset", OFFSET);
  query.set("limit", PAGE_SIZE);
  const run = await getJSON("api/run?" + query);
  if (mine !== LOADING) return; // a later filter or page was asked for meanwhile
  for (const name of FILTERS.slice(0, 3)) fillSelect(name, run.facets[name]);
  document.getElementById("title").textContent = `run ${run.name}`;
  document.getElementById("run-dir").textContent = `${run.run_dir} · frames kept: ${FRAMES_KEPT[run.frames_kept] || run.frames_kept}`;
  render(run);
  showRadar(query.get("model"), query.get("track"));
  const params = new URLSearchParams();
  for (const [name, value] of chosen()) params.set("f-" + name, value);
  if (OFFSET) params.set("offset", OFFSET);
  history.replaceState(null, "", params.toString() ? "?" + params : location.pathname);
  document.body.dataset.ready = "1";
}

// The chosen model's radar beside its episodes; hidden for all models or none annotated.
function showRadar(model, track) {
  const figure = document.getElementById("radar");
  const img = document.getElementById("radar-img");
  if (!model) { figure.hidden = true; img.removeAttribute("src"); return; }
  const query = new URLSearchParams({ model });
  if (track) query.set("track", track);
  img.onload = () => { figure.hidden = false; };
  img.onerror = () => { figure.hidden = true; };
  img.src = "api/radar?" + query;
}

function show(error) {
  document.body.append(el("p", { class: "error" }, String(error)));
}

function main() {
  const params = new URLSearchParams(location.search);
  for (const name of FILTERS) {
    const select = document.getElementById("f-" + name);
    const value = params.get("f-" + name);
    if (value && name !== "outcome") select.append(el("option", { value }, value));
    if (value) select.value = value;
    select.addEventListener("change", () => { OFFSET = 0; load().catch(show); });
  }
  OFFSET = Math.max(0, Number(params.get("offset")) || 0);
  document.getElementById("prev-page").addEventListener("click", () => {
    OFFSET = Math.max(0, OFFSET - PAGE_SIZE);
    load().catch(show);
  });
  document.getElementById("next-page").addEventListener("click", () => {
    OFFSET += PAGE_SIZE;
    load().catch(show);
  });
  const who = document.getElementById("annotator");
  who.value = annotatorName();
  who.addEventListener("change", () => setAnnotatorName(who.value.trim()));
  return load();
}

main().catch(show);
