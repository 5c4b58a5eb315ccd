"use strict";

let EPISODES = [];

function fillSelect(id, values) {
  const select = document.getElementById(id);
  for (const v of [...new Set(values)].sort()) select.append(el("option", { value: v }, v));
}

function outcomeOf(e) {
  return e.scored ? (e.success ? "success" : "failure") : "unscored";
}

function render() {
  const f = (id) => document.getElementById(id).value;
  const shown = EPISODES.filter((e) =>
    (!f("f-model") || e.model === f("f-model")) &&
    (!f("f-track") || e.track === f("f-track")) &&
    (!f("f-task") || e.task === f("f-task")) &&
    (!f("f-outcome") || outcomeOf(e) === f("f-outcome")));
  const body = document.querySelector("#episodes tbody");
  body.replaceChildren(...shown.map((e) => el("tr", { "data-id": e.id, class: outcomeOf(e) },
    el("td", {}, el("a", { href: episodeUrl(e.id) }, e.id)),
    el("td", {}, e.model), el("td", {}, e.track), el("td", {}, e.task),
    el("td", {}, e.seed), el("td", {}, e.run),
    el("td", { class: "outcome" }, e.scored ? (e.success ? "✓ success" : "✗ failure") : e.status),
    el("td", {}, e.stop_reason), el("td", {}, `${e.steps_used}/${e.step_budget}`),
    el("td", {}, checkpointsText(e)),
    el("td", {}, e.annotators.join(", ")))));
  document.getElementById("count").textContent = `${shown.length} of ${EPISODES.length} episodes`;
  // The episode page's n/p keys walk this filtered order.
  sessionStorage.setItem(ORDER_KEY, JSON.stringify(shown.map((e) => e.id)));
  const params = new URLSearchParams();
  for (const id of ["f-model", "f-track", "f-task", "f-outcome"]) if (f(id)) params.set(id, f(id));
  history.replaceState(null, "", params.toString() ? "?" + params : "/");
}

async function main() {
  const run = await getJSON("/api/run");
  EPISODES = run.episodes;
  document.getElementById("title").textContent = `run ${run.name}`;
  document.getElementById("run-dir").textContent = run.run_dir;
  fillSelect("f-model", EPISODES.map((e) => e.model));
  fillSelect("f-track", EPISODES.map((e) => e.track));
  fillSelect("f-task", EPISODES.map((e) => e.task));
  const params = new URLSearchParams(location.search);
  for (const id of ["f-model", "f-track", "f-task", "f-outcome"]) {
    const select = document.getElementById(id);
    if (params.get(id)) select.value = params.get(id);
    select.addEventListener("change", render);
  }
  const who = document.getElementById("annotator");
  who.value = annotatorName();
  who.addEventListener("change", () => setAnnotatorName(who.value.trim()));
  render();
  document.body.dataset.ready = "1";
}

main().catch((err) => document.body.append(el("p", { class: "error" }, String(err))));
