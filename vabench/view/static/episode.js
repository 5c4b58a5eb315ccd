"use strict";

const EPISODE = new URLSearchParams(location.search).get("id") || "";
let RUBRIC = null;
let STATE = null;
let current = 0;

function frameUrl(file) {
  return `api/frame?episode=${encodeURIComponent(EPISODE)}&file=${encodeURIComponent(file)}`;
}

function viewOfFrame(file, fallback) {
  const m = /step_\d+_\d+_(.+)\.jpg$/.exec(file);
  return m ? m[1] : fallback;
}

function yesNo(v) {
  return v === null || v === undefined ? "—" : v ? "yes" : "NO";
}

function kv(obj) {
  return el("table", { class: "kv" }, Object.entries(obj || {}).map(([k, v]) =>
    el("tr", {}, el("th", {}, k), el("td", {}, typeof v === "object" ? JSON.stringify(v) : String(v)))));
}

function robotState(robot) {
  return el("table", { class: "kv" }, Object.entries(robot || {}).map(([arm, s]) =>
    el("tr", {}, el("th", {}, arm), el("td", {},
      `GC ${JSON.stringify(s.finger_center_xyz)} · ${s.is_open ? "open" : "closed"} · ` +
      `rpy ${JSON.stringify(s.control_eepose_rpy_deg)}`))));
}

function evaluatorPanel(ev, title) {
  if (!ev) return null;
  const objects = Object.entries(ev.objects || {}).map(([name, p]) =>
    el("tr", {}, el("th", {}, name), el("td", {}, `pos ${JSON.stringify(p.pos)} quat ${JSON.stringify(p.quat)}`)));
  return el("details", { class: "evaluator" },
    el("summary", {}, title || "EVALUATOR-ONLY — never sent to any model"),
    "checks" in ev ? el("div", {}, "predicate checks: ", kv(ev.checks)) : null,
    "progress" in ev ? el("div", {}, `checkpoint progress ${ev.progress}, success ${yesNo(ev.success)}`) : null,
    objects.length ? el("table", { class: "kv" }, objects) : null);
}

function stepCard(card) {
  const a = card.action;
  const failed = a && !(a.valid && a.planner_success);
  return el("article", { class: "step" + (failed ? " failed" : ""), "data-step": card.step, id: `step-${card.step}` },
    el("h3", {}, `Step ${card.step}`, el("span", { class: "muted" }, ` view: ${card.view || "—"}`)),
    el("div", { class: "frames" }, card.frames.map((f) =>
      el("figure", {}, el("img", { class: "frame", src: frameUrl(f), alt: f, loading: "lazy" }),
        el("figcaption", {}, viewOfFrame(f, card.view || ""))))),
    card.replies.map((r, i) => el("div", { class: "reply" },
      el("div", { class: "muted" }, `model reply ${i + 1}`), el("pre", {}, r.text))),
    card.rejections.map((r) => el("div", { class: "rejected" }, `rejected (${r.field}): ${r.message}`)),
    card.tools.map((t) => el("div", { class: "tool" }, `tool ${t.label}: `, el("pre", {}, String(t.result)))),
    card.decision ? el("div", { class: "decision" },
      el("strong", {}, `${card.decision.kind}: ${card.decision.label}`),
      card.decision.reason ? ` — ${card.decision.reason}` : "") : null,
    card.camera ? el("div", {}, `camera → ${card.camera.view}`) : null,
    a ? el("div", { class: "result" + (failed ? " bad" : "") },
      `valid ${yesNo(a.valid)} · planner ${yesNo(a.planner_success)} · executed ${yesNo(a.executed)}` +
      ` · clipped ${JSON.stringify(a.clipped)} · executed_mm ${JSON.stringify(a.executed_mm)}` +
      (a.error ? ` · error: ${a.error}` : "")) : null,
    card.robot ? robotState(card.robot) : null,
    evaluatorPanel(card.evaluator));
}

function setStep(i, scroll = true) {
  const cards = document.querySelectorAll("#steps .step");
  if (!cards.length) return;
  current = Math.max(0, Math.min(cards.length - 1, i));
  cards.forEach((c, k) => c.classList.toggle("current", k === current));
  if (scroll) cards[current].scrollIntoView({ block: "nearest" });
  document.body.dataset.step = cards[current].dataset.step;
}

function goStep(step) {
  const cards = [...document.querySelectorAll("#steps .step")];
  const i = cards.findIndex((c) => Number(c.dataset.step) === step);
  if (i >= 0) setStep(i);
}

// The episodes before and after this one in the run page's filtered order (its filters are in
// sessionStorage; the server finds the neighbours, however many episodes pass them).
let NEIGHBOURS = { previous: null, next: null };

async function loadNeighbours() {
  const filters = sessionStorage.getItem(ORDER_KEY) || "";
  const query = new URLSearchParams(filters.startsWith("[") ? "" : filters);
  query.set("id", EPISODE);
  NEIGHBOURS = await getJSON("api/neighbours?" + query);
}

function neighbour(delta) {
  return delta > 0 ? NEIGHBOURS.next : NEIGHBOURS.previous;
}

function goEpisode(delta) {
  const id = neighbour(delta);
  if (id) location.href = episodeUrl(id);
}

function buttons(item, disabledWhy) {
  const own = STATE ? STATE.own[item] : undefined;
  const make = (value, text) => el("button", {
    class: "vote" + (own === value || (value === null && own === undefined) ? " chosen" : ""),
    "data-item": item, "data-value": value === null ? "null" : value,
    disabled: !!disabledWhy || !annotatorName(),
    onclick: () => vote(item, value),
  }, text);
  return el("span", { class: "buttons" }, make(1, "1 yes"), make(0, "0 no"), make(null, "clear"));
}

function renderPanel() {
  const gates = document.getElementById("gates");
  gates.replaceChildren(...RUBRIC.gates.map((g) => {
    const info = STATE ? STATE.gates[g.code] : null;
    return el("div", { class: "item gate", "data-code": g.code },
      el("div", {}, el("strong", {}, g.name), " ", buttons(g.code, "")),
      el("div", {}, g.question),
      el("div", { class: "muted" }, info ? `majority of ${info.votes} vote(s): ${info.majority ?? "—"} · activates ${g.activates.join(", ")}` : ""),
      el("details", {}, el("summary", {}, "rubric"), g.rubric));
  }));
  const criteria = document.getElementById("criteria");
  criteria.replaceChildren(...Object.entries(RUBRIC.modules).map(([module, title]) =>
    el("div", { class: "module" }, el("h4", {}, `${module}: ${title}`),
      RUBRIC.criteria.filter((c) => c.module === module).map((c) => {
        const why = STATE ? STATE.not_activated[c.code] : "";
        return el("div", { class: "item" + (why ? " inactive" : ""), "data-code": c.code },
          el("div", {}, el("strong", {}, `${c.code} ${c.name}`), " ", buttons(c.code, why)),
          el("div", {}, c.summary),
          why ? el("div", { class: "muted" }, `not activated: ${c.gate} gate is 0`) : null,
          el("details", {}, el("summary", {}, "rubric"), c.rubric));
      }))));
}

async function loadState() {
  const who = annotatorName();
  STATE = null;
  if (who) {
    try {
      STATE = await getJSON(`api/annotations?episode=${encodeURIComponent(EPISODE)}&annotator=${encodeURIComponent(who)}`);
    } catch (err) {
      setStatus(String(err.message || err), true);
    }
  } else {
    setStatus("enter your annotator name to annotate", true);
  }
  renderPanel();
}

function setStatus(text, bad) {
  const s = document.getElementById("status");
  s.textContent = text;
  s.className = bad ? "error" : "muted";
}

async function vote(item, value) {
  try {
    STATE = await postJSON("api/judgment", { annotator: annotatorName(), episode: EPISODE, item, value });
    setStatus(`saved ${item} = ${value === null ? "cleared" : value} at ${new Date().toLocaleTimeString()}`);
  } catch (err) {
    setStatus(String(err.message || err), true);
  }
  renderPanel();
}

function renderHints(hints) {
  document.getElementById("hints").replaceChildren(...hints.map((h) =>
    el("li", { class: h.source === "evaluator" ? "evaluator-hint" : "" },
      el("a", { href: `#step-${h.step}`, onclick: (ev) => { ev.preventDefault(); goStep(h.step); } }, `step ${h.step}`),
      ` ${h.item}: ${h.text}`, h.source === "evaluator" ? " [evaluator-only state]" : "")));
}

async function main() {
  [RUBRIC] = await Promise.all([getJSON("api/rubric")]);
  const ep = await getJSON(`api/episode?id=${encodeURIComponent(EPISODE)}`);
  const s = ep.summary;
  document.title = `episode ${ep.id}`;
  document.getElementById("title").textContent = ep.id;
  document.getElementById("instruction").textContent = `instruction: ${ep.instruction}`;
  document.getElementById("frames-note").textContent = ep.frames_note || "";
  document.getElementById("outcome").replaceChildren(
    el("span", { class: s.success ? "good" : "bad" }, s.scored ? (s.success ? "✓ success" : "✗ failure") : s.status),
    ` · stop: ${s.stop_reason} · steps ${s.steps_used}/${s.step_budget} · checkpoints ${checkpointsText(s)}` +
    ` · ${s.robot_actions} robot, ${s.camera_actions} camera, ${s.invalid_actions} failed actions`,
    evaluatorPanel(ep.reset, "EVALUATOR-ONLY — state after reset (never sent to any model)"));
  document.getElementById("steps").replaceChildren(...ep.steps.map(stepCard));
  await loadNeighbours();
  document.getElementById("prev-episode").disabled = !neighbour(-1);
  document.getElementById("next-episode").disabled = !neighbour(1);
  document.getElementById("prev-episode").addEventListener("click", () => goEpisode(-1));
  document.getElementById("next-episode").addEventListener("click", () => goEpisode(1));
  document.querySelectorAll("#steps .step").forEach((c, i) => c.addEventListener("click", () => setStep(i, false)));
  renderHints(ep.hints);
  const who = document.getElementById("annotator");
  who.value = annotatorName();
  who.addEventListener("change", async () => { setAnnotatorName(who.value.trim()); setStatus(""); await loadState(); });
  setStep(0, false);
  await loadState();
  document.body.dataset.ready = "1";
}

document.addEventListener("keydown", (ev) => {
  if (ev.target instanceof HTMLInputElement || ev.altKey || ev.ctrlKey || ev.metaKey) return;
  if (ev.key === "ArrowRight" || ev.key === "j") setStep(current + 1);
  else if (ev.key === "ArrowLeft" || ev.key === "k") setStep(current - 1);
  else if (ev.key === "n") goEpisode(1);
  else if (ev.key === "p") goEpisode(-1);
  else return;
  ev.preventDefault();
});

main().catch((err) => { setStatus(String(err.message || err), true); document.body.dataset.ready = "error"; });
