// The review page: the folder's episodes (GET /api/episodes), one video at a time, verdicts by key or by the
// buttons beside the video (POST /api/verdict), shown on the row at once and taken back if the server refuses.
// Sorting, filtering and paging happen here; the server sends the list once (again after a lost connection:
// a banner says so while the server does not answer, and goes when it answers again).
"use strict";
const PAGE = 100;
const state = { rows: [], view: [], sortKey: "id", sortDir: 1, page: 0, selected: null };
const $ = (id) => document.getElementById(id);
const COLORS = ["#4670c8", "#c88c3c"];

function esc(text) {
  return String(text ?? "").replace(/[&<>"']/g, (c) => ({ "&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;" })[c]);
}

function applyView() {
  const text = $("filter").value.trim().toLowerCase();
  const verdict = $("f-verdict").value, success = $("f-success").value, flag = $("f-flag").value;
  state.view = state.rows.filter((r) => {
    if (verdict === "none" ? r.verdict : verdict && r.verdict !== verdict) return false;
    if (success && r.success !== (success === "yes")) return false;
    if (flag === "none" && r.flags.length) return false;
    if (flag === "some" && !r.flags.length) return false;
    if (flag.startsWith("flag:") && !r.flags.includes(flag.slice(5))) return false;
    if (text) {
      const hay = [r.id, r.task, r.source, r.flags.join(" "), r.note || "", r.verdict || ""].join(" ").toLowerCase();
      if (!hay.includes(text)) return false;
    }
    return true;
  });
  const key = state.sortKey, dir = state.sortDir;
  const value = (r) => key === "flags" ? r.flags.length : (r[key] ?? "");
  state.view.sort((a, b) => { const x = value(a), y = value(b); return (x < y ? -1 : x > y ? 1 : 0) * dir; });
  state.page = Math.min(state.page, Math.max(0, Math.ceil(state.view.length / PAGE) - 1));
  render();
}

function render() {
  const start = state.page * PAGE;
  const rows = state.view.slice(start, start + PAGE);
  $("rows").innerHTML = rows.map((r) => `
    <tr data-id="${esc(r.id)}" tabindex="0" class="${r.id === state.selected ? "sel" : ""}"${r.id === state.selected ? ' aria-selected="true"' : ""}>
      <td><img class="thumb" loading="lazy" src="thumb/${encodeURIComponent(r.id)}.png" alt=""></td>
      <td>${esc(r.id)}</td><td>${esc(r.task)}</td><td>${esc(r.source)}</td>
      <td>${r.success ? "yes" : "no"}</td><td>${Number(r.duration_s).toFixed(1)} s</td>
      <td>${r.flags.map((f) => `<span class="flag">${esc(f)}</span>`).join("")}</td>
      <td class="verdict ${esc(r.verdict || "")}${r.pending ? " pending" : ""}">${esc(r.verdict || "")}${r.note ? " ✎" : ""}</td>
    </tr>`).join("");
  const pages = Math.max(1, Math.ceil(state.view.length / PAGE));
  $("page").textContent = `page ${state.page + 1} / ${pages}`;
  $("count").textContent = `${state.view.length} of ${state.rows.length} episodes`;
  showButtons();
}

function selectedRow() {
  return state.rows.find((r) => r.id === state.selected);
}

function showButtons() {  // the buttons beside the video say the selected episode's verdict
  const row = selectedRow();
  for (const [id, verdict] of [["accept-btn", "accept"], ["reject-btn", "reject"]]) {
    $(id).disabled = !row;
    $(id).setAttribute("aria-pressed", String(Boolean(row && row.verdict === verdict)));
  }
  $("note-btn").disabled = !row;
}

function select(id) {
  const row = state.rows.find((r) => r.id === id);
  if (!row) return;
  if (state.selected !== id) closeNote();
  state.selected = id;
  const index = state.view.findIndex((r) => r.id === id);
  if (index >= 0) state.page = Math.floor(index / PAGE);
  render();
  $("title").textContent = `${row.id} · ${row.task}`;
  $("details").innerHTML = `source: ${esc(row.source)} · success: ${row.success ? "yes" : "no"} · `
    + `${Number(row.duration_s).toFixed(2)} s · flags: ${esc(row.flags.join(", ") || "none")}`
    + (row.verdict ? ` · <span class="${esc(row.verdict)}">${esc(row.verdict)}</span> by ${esc(row.reviewer)}` : "")
    + (row.note ? ` · note: ${esc(row.note)}` : "");
  const player = $("player");
  if (player.dataset.episode !== row.id) {  // a verdict or a reload keeps the video where it is
    player.dataset.episode = row.id;
    player.src = `video/${encodeURIComponent(row.id)}.mp4`;
    player.play().catch(() => {});
  }
  const bar = $("bar");
  const steps = Math.max(1, row.steps);
  bar.innerHTML = row.subtasks.map((s, i) => `<div class="seg" title="${esc(s.object)}" style="left:${100 * s.start / steps}%;`
    + `width:${100 * (s.end - s.start) / steps}%;background:${COLORS[i % 2]}"></div>`).join("") + '<div class="cursor" id="cursor"></div>';
}

function move(delta) {
  if (!state.view.length) return;
  const index = state.view.findIndex((r) => r.id === state.selected);
  const next = index < 0 ? 0 : Math.min(state.view.length - 1, Math.max(0, index + delta));
  select(state.view[next].id);
}

async function record(verdict, note) {
  const row = selectedRow();
  if (!row) return;
  const reviewer = $("reviewer").value.trim();
  if (!reviewer) { $("status").textContent = "type your name in 'reviewer' first"; $("reviewer").focus(); return; }
  localStorage.setItem("teleop-reviewer", reviewer);
  const body = { episode: row.id, verdict: verdict === undefined ? row.verdict : verdict, reviewer,
                 note: note === undefined ? (row.note || "") : note };
  const before = { verdict: row.verdict, reviewer: row.reviewer, note: row.note, reviewed_at: row.reviewed_at };
  Object.assign(row, { verdict: body.verdict, reviewer, note: body.note, pending: true });  // on the row at once
  $("status").textContent = `${row.id}: saving ${body.verdict || "note"}…`;
  applyView();
  let answer, got;
  try {
    answer = await request("api/verdict", { method: "POST", headers: { "Content-Type": "application/json" },
                                            body: JSON.stringify(body) });
    got = await answer.json();
  } catch (error) {
    Object.assign(row, before, { pending: false });
    $("status").textContent = `not saved (the server did not answer): ${row.id}`;
    applyView();
    return;
  }
  if (!answer.ok) {
    Object.assign(row, before, { pending: false });
    $("status").textContent = `not saved: ${got.error}`;
    applyView();
    return;
  }
  Object.assign(row, { verdict: got.verdict, reviewer: got.reviewer, note: got.note, reviewed_at: got.time, pending: false });
  $("status").textContent = `${row.id}: ${got.verdict || "note"} saved by ${got.reviewer}`;
  applyView();
  if (state.selected === row.id) select(row.id);
}

function openNote() {
  const row = selectedRow();
  if (!row) return;
  $("note-text").value = row.note || "";
  $("note-form").hidden = false;
  $("note-btn").setAttribute("aria-expanded", "true");
  $("note-text").focus();
}

function closeNote() {
  $("note-form").hidden = true;
  $("note-btn").setAttribute("aria-expanded", "false");
}

document.addEventListener("keydown", (event) => {
  if (["INPUT", "TEXTAREA", "SELECT"].includes(event.target.tagName) || event.ctrlKey || event.metaKey || event.altKey) return;
  if (event.key === "j") move(1);
  else if (event.key === "k") move(-1);
  else if (event.key === "a") record("accept");
  else if (event.key === "r") record("reject");
  else if (event.key === "n" && state.selected) openNote();
  else if (event.key === "Enter" && event.target.closest && event.target.closest("#rows tr")) select(event.target.closest("tr").dataset.id);
  else return;
  event.preventDefault();
});

$("accept-btn").addEventListener("click", () => record("accept"));
$("reject-btn").addEventListener("click", () => record("reject"));
$("note-btn").addEventListener("click", () => ($("note-form").hidden ? openNote() : closeNote()));
$("note-cancel").addEventListener("click", closeNote);
$("note-form").addEventListener("submit", (event) => {
  event.preventDefault();
  const note = $("note-text").value;
  closeNote();
  record(undefined, note);
});
$("note-text").addEventListener("keydown", (event) => {
  if (event.key === "Escape") { closeNote(); $("note-btn").focus(); }
});

$("rows").addEventListener("click", (event) => {
  const tr = event.target.closest("tr");
  if (tr) select(tr.dataset.id);
});
document.querySelectorAll("th[data-key]").forEach((th) => th.addEventListener("click", () => {
  state.sortDir = state.sortKey === th.dataset.key ? -state.sortDir : 1;
  state.sortKey = th.dataset.key;
  applyView();
}));
["filter", "f-verdict", "f-success", "f-flag"].forEach((id) => $(id).addEventListener("input", () => { state.page = 0; applyView(); }));
$("prev-page").addEventListener("click", () => { state.page = Math.max(0, state.page - 1); render(); });
$("next-page").addEventListener("click", () => { state.page = Math.min(Math.ceil(state.view.length / PAGE) - 1, state.page + 1); render(); });
$("player").addEventListener("timeupdate", () => {
  const row = state.rows.find((r) => r.id === state.selected), cursor = $("cursor"), player = $("player");
  if (row && cursor && player.duration) cursor.style.left = `${100 * player.currentTime / player.duration}%`;
});

// -- the connection: a banner while the server does not answer, the list read again when it does ---------
let lost = false;
let listed = false;

function disconnected() {
  if (lost) return;
  lost = true;
  $("banner").hidden = false;
  document.body.dataset.connection = "lost";
}

let reloading = false;

async function reconnected() {
  if (!lost || reloading) return;
  reloading = true;
  try {
    await load();  // the state again: verdicts written meanwhile (by another reviewer too), episodes added
  } catch (error) {
    return;  // not yet: the next heartbeat tries again
  } finally {
    reloading = false;
  }
  lost = false;
  $("banner").hidden = true;
  document.body.dataset.connection = "ok";
}

async function request(url, options) {  // fetch, and the banner when the server does not answer
  try {
    const answer = await fetch(url, options);
    if (answer.status >= 502 && answer.status <= 504) throw new Error(`the server answered ${answer.status}`);
    if (lost) reconnected();
    return answer;
  } catch (error) {
    disconnected();
    throw error;
  }
}

async function heartbeat() {  // noticed while nobody clicks, too
  try {
    await request("api/info", { cache: "no-store" });
  } catch (error) {
    // the banner is up; the next beat tries again
  }
}

async function load() {
  const info = await (await fetch("api/info")).json();
  $("folder").textContent = info.folder;
  if (!listed) $("reviewer").value = localStorage.getItem("teleop-reviewer") || info.reviewer || "";
  const t0 = performance.now();
  const rows = await (await fetch("api/episodes")).json();
  window.__listMs = performance.now() - t0;
  state.rows = rows;
  const seen = [...new Set(state.rows.flatMap((r) => r.flags))].sort();
  document.querySelectorAll("#f-flag option[value^='flag:']").forEach((option) => option.remove());
  $("f-flag").insertAdjacentHTML("beforeend", seen.map((f) => `<option value="flag:${esc(f)}">${esc(f)}</option>`).join(""));
  applyView();
  if (state.selected && state.rows.some((r) => r.id === state.selected)) select(state.selected);
  else if (state.view.length) select(state.view[0].id);
  listed = true;
  document.body.dataset.ready = "1";
}

load().catch(() => disconnected());
setInterval(heartbeat, 2000);
