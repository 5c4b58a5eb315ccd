// Shared helpers of the viewer's pages. Every value from the run is inserted as text
// (textContent, attributes via setAttribute), never parsed as HTML.
"use strict";

function el(tag, attrs, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs || {})) {
    if (value === null || value === undefined || value === false) continue;
    if (key === "class") node.className = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else node.setAttribute(key, value === true ? "" : String(value));
  }
  for (const child of children.flat()) {
    if (child === null || child === undefined) continue;
    node.append(child instanceof Node ? child : document.createTextNode(String(child)));
  }
  return node;
}

async function getJSON(url) {
  const response = await fetch(url);
  const body = await response.json();
  if (!response.ok) throw new Error(body.error || response.statusText);
  return body;
}

async function postJSON(url, data) {
  const response = await fetch(url, {
    method: "POST",
    headers: { "Content-Type": "application/json" },
    body: JSON.stringify(data),
  });
  const body = await response.json();
  if (!response.ok) throw new Error(body.error || response.statusText);
  return body;
}

const ANNOTATOR_KEY = "vabench.annotator";
const ORDER_KEY = "vabench.episodeOrder";

function annotatorName() {
  return localStorage.getItem(ANNOTATOR_KEY) || "";
}

function setAnnotatorName(name) {
  localStorage.setItem(ANNOTATOR_KEY, name);
}

function episodeUrl(id) {
  return "episode?id=" + encodeURIComponent(id);
}

function checkpointsText(e) {
  return `${e.progress}/${e.n_checkpoints}` +
    (e.checkpoints_reached.length ? ` (${e.checkpoints_reached.join(", ")})` : "");
}
