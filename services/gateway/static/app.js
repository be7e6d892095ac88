// The LSR plan viewer: plain JavaScript, no library, no build step. Talks to this gateway only.
"use strict";

const $ = (id) => document.getElementById(id);
const SVG = "http://www.w3.org/2000/svg";
const BOX_COLOURS = {
  red: "#d92d20", green: "#2e9d4f", blue: "#2563eb", yellow: "#e0a800", orange: "#f08a1c",
};
const ui = { task: null, info: null, graph: null, ends: {}, plans: [], selected: 0, healthTimer: null,
  roadmapLoading: false, roadmapLoads: 0, roadmapRetry: false };

// --- small helpers ------------------------------------------------------------------------
function el(tag, attrs = {}, ...children) {
  const node = document.createElement(tag);
  for (const [key, value] of Object.entries(attrs)) {
    if (key === "text") node.textContent = value;
    else if (key.startsWith("on")) node.addEventListener(key.slice(2), value);
    else if (value !== null && value !== undefined && value !== false) node.setAttribute(key, value);
  }
  for (const child of children) if (child) node.append(child);
  return node;
}
function svgEl(tag, attrs = {}) {
  const node = document.createElementNS(SVG, tag);
  for (const [key, value] of Object.entries(attrs)) node.setAttribute(key, value);
  return node;
}
function headers(json = true) {
  const out = json ? { "content-type": "application/json" } : {};
  const key = sessionStorage.getItem("lsr-api-key");
  if (key) out.authorization = "Bearer " + key;
  return out;
}

class ApiError extends Error {
  constructor(status, detail) {
    super(typeof detail === "string" ? detail : JSON.stringify(detail));
    this.status = status;
    this.detail = detail;
  }
}

async function api(method, path, body) {
  let reply;
  try {
    reply = await fetch(path, {
      method, headers: headers(body !== undefined),
      body: body === undefined ? undefined : JSON.stringify(body),
    });
  } catch (err) {
    throw new ApiError(0, "the gateway cannot be reached (" + err.message + ")");
  }
  if (!reply.ok) {
    let detail = reply.statusText;
    try { detail = (await reply.json()).detail; } catch (_) { /* not JSON */ }
    throw new ApiError(reply.status, detail);
  }
  return reply;
}

// --- errors in plain words, next to the field they name ------------------------------------
const FIELD_NAMES = { start: "Start", goal: "Goal", max_plans: "Plans at most", task: "Task" };

function clearErrors() {
  for (const node of document.querySelectorAll(".error")) node.textContent = "";
}

function statusWords(status) {
  return {
    0: "No answer", 401: "An API key is needed (open “API key” above)", 404: "Not found",
    408: "The request took too long to arrive", 413: "The request is too large",
    415: "Wrong content type", 422: "Not accepted", 502: "A service failed",
    503: "A service is unavailable",
  }[status] || "Error " + status;
}

// Where an error goes: the field's own slot when the API names one, else `fallback`.
function showError(err, fallback = "request-error") {
  if (!(err instanceof ApiError)) {
    $(fallback).textContent = "Unexpected problem: " + err.message;
    return;
  }
  const items = Array.isArray(err.detail) ? err.detail : [{ loc: null, msg: String(err.detail) }];
  for (const item of items) {
    let loc = Array.isArray(item.loc) ? item.loc.filter((p) => p !== "body") : [];
    if (!loc.length) {  // a plain-string detail may still name its field: "... (start.image)"
      const named = /\b(start|goal)\.(image|state)\b/.exec(item.msg || "");
      if (named) loc = [named[1], named[2]];
    }
    const target = FIELD_NAMES[loc[0]] && $(loc[0] + "-error") ? loc[0] + "-error" : fallback;
    const where = loc.length ?
      [FIELD_NAMES[loc[0]] || loc[0], ...loc.slice(1)].join(" ").replaceAll("_", " ") + ": " : "";
    let msg = (item.msg || "").replace(/^Value error, /, "");
    if (loc.length && msg.startsWith(loc.join(".") + ": ")) msg = msg.slice(loc.join(".").length + 2);
    const text = statusWords(err.status) + ". " + where + msg;
    const slot = $(target);
    slot.textContent = slot.textContent ? slot.textContent + " " + text : text;
  }
}

// --- states in words ------------------------------------------------------------------------
function stateText(state) {
  if (!state) return "state unknown";
  if (state.stacks) {
    return state.stacks.map((c) => "[" + c.map((b) => b[0].toUpperCase()).join("") + "]").join(" ");
  }
  if (state.boxes && "rope" in state) {
    const boxes = Object.entries(state.boxes).map(([b, c]) => `${b} (${c.row},${c.col})`);
    const rope = state.rope ?
      `rope round (${state.rope.pillar.row},${state.rope.pillar.col}), on its ${state.rope.turn}` :
      "rope straight";
    return [...boxes, rope].join(" · ");
  }
  if (state.folds) {
    // a view names the folds a camera above cannot see: unknown, folded or not
    const hidden = (state.hidden || []).map((f) => `${f.replace("_", " ")} unknown`);
    return [state.folds.length ? state.folds.join(", ") : "flat", ...hidden].join(" · ");
  }
  return JSON.stringify(state);
}
function actionText(action) {
  if (!action) return "no action";
  const cell = (c) => `(${c.row},${c.col})`;
  if (action.kind === "rope") return `rope over ${cell(action.pillar)}`;
  if (action.kind === "box") return `push ${cell(action.pick)} → ${cell(action.release)}`;
  const height = action.height === undefined ? "" : ` h${action.height}`;
  return `${cell(action.pick)} → ${cell(action.release)}${height}`;
}

// --- start and goal ---------------------------------------------------------------------------
function emptyState() {
  if (ui.info.levels) return { stacks: Array.from({ length: ui.info.columns }, () => []) };
  if (ui.info.folds) return { folds: [] };
  if (ui.info.pillars) return defaultState("start");
  return null;
}
function randomState() {
  if (ui.info.pillars) return randomRopeBox();
  if (ui.info.levels) {
    const stacks = Array.from({ length: ui.info.columns }, () => []);
    const boxes = [...ui.info.boxes].sort(() => Math.random() - 0.5);
    for (const box of boxes) {
      const open = stacks.filter((c) => c.length < ui.info.levels);
      open[Math.floor(Math.random() * open.length)].push(box);
    }
    return { stacks };
  }
  if (ui.info.folds) return { folds: ui.info.folds.filter(() => Math.random() < 0.5) };
  return null;
}
function defaultState(name) {
  if (ui.info.pillars) {
    // start: side by side, the rope straight; goal: side by side above, bent round a pillar
    return name === "start" ?
      { boxes: { green: { row: 1, col: 0 }, orange: { row: 1, col: 1 } }, rope: null } :
      { boxes: { green: { row: 0, col: 0 }, orange: { row: 0, col: 1 } },
        rope: { pillar: { row: 0, col: 0 }, turn: "left" } };
  }
  if (ui.info.levels) {
    const boxes = ui.info.boxes;  // start: one box a column; goal: a tower on the middle column
    if (name === "start") {
      const stacks = Array.from({ length: ui.info.columns }, () => []);
      boxes.forEach((b, i) => stacks[i % ui.info.columns].push(b));
      return { stacks };
    }
    const stacks = Array.from({ length: ui.info.columns }, () => []);
    boxes.forEach((b, i) => stacks[i < ui.info.levels ? 1 : 2].push(b));
    return { stacks };
  }
  if (ui.info.folds) return { folds: name === "start" ? [] : [ui.info.folds[0]] };
  return null;
}

function buildEndpoint(name) {
  const root = $(name);
  root.replaceChildren();
  const title = name === "start" ? "Start" : "Goal";
  const end = { name, state: defaultState(name), image: null, held: null };
  ui.ends[name] = end;
  const preview = el("img", { class: "preview", alt: title + " image", id: name + "-image" });
  const editor = el("div", { class: "editor", id: name + "-editor" });
  const upload = el("input", {
    type: "file", accept: "image/png,image/jpeg", id: name + "-upload",
    "aria-label": title + ": upload a PNG or JPEG camera image",
    onchange: (e) => useUpload(end, e.target.files[0]),
  });
  const tools = el("div", { class: "tools" });
  if (end.state) {
    tools.append(el("button", {
      type: "button", id: name + "-random", text: "Random state",
      onclick: () => { end.state = randomState(); end.image = null; refresh(end); },
    }));
  }
  tools.append(el("label", {}, "Upload image ", upload));
  const source = el("p", { class: "muted", id: name + "-source" });
  root.append(
    el("h2", { text: title }), el("div", {}, preview, source), editor, tools,
    el("p", { class: "error", id: name + "-error", role: "alert" }),
  );
  end.preview = preview;
  end.editor = editor;
  end.source = source;
  refresh(end);
}

function useUpload(end, file) {
  $(end.name + "-error").textContent = "";
  if (!file) return;
  if (!["image/png", "image/jpeg"].includes(file.type)) {
    $(end.name + "-error").textContent = "Choose a PNG or JPEG file (this one is " +
      (file.type || "of unknown type") + ").";
    return;
  }
  // plan() waits for this: a Plan pressed at once would otherwise send the end as it was
  end.reading = new Promise((resolve) => {
    const reader = new FileReader();
    reader.onload = () => { end.image = reader.result; refresh(end); resolve(); };
    reader.onerror = () => resolve();
    reader.readAsDataURL(file);
  });
}

// The endpoint as the API takes it.
function endpointBody(end) {
  return end.image ? { image: end.image } : { state: end.state };
}

// Each end's renders in order: a reply that comes after the end has changed (another state,
// an uploaded image, another task's editor built in its place) touches neither its picture nor
// its error slot, which may by then hold a plan's error for the new end.
async function refresh(end) {
  drawEditor(end);
  const seq = end.renderSeq = (end.renderSeq || 0) + 1;
  if (end.image) {
    end.preview.src = end.image;
    end.source.textContent = "uploaded image";
    return;
  }
  if (!end.state) {
    end.preview.removeAttribute("src");
    end.source.textContent = "upload an image: this task has no state editor";
    return;
  }
  end.source.textContent = stateText(end.state);
  try {
    const reply = await api("POST", "/render", { task: ui.task, state: end.state, seed: 0 });
    const body = await reply.json();
    if (stale(end, seq)) return;
    end.preview.src = "data:image/png;base64," + body.image;
    $(end.name + "-error").textContent = "";
  } catch (err) {
    if (stale(end, seq)) return;
    $(end.name + "-error").textContent = "";
    showError(err, end.name + "-error");
  }
}

function stale(end, seq) {
  return seq !== end.renderSeq || ui.ends[end.name] !== end;
}

function drawEditor(end) {
  const editor = end.editor;
  editor.replaceChildren();
  if (!end.state) return;
  if (end.image) {
    editor.append(el("button", {
      type: "button", text: "Use the state editor again",
      onclick: () => { end.image = null; $(end.name + "-upload").value = ""; refresh(end); },
    }));
    return;
  }
  if (ui.info.levels) drawBoxes(end);
  else if (ui.info.folds) drawFolds(end);
  else if (ui.info.pillars) drawRopeBox(end);
}

// Box stacking: pick the top box of a column, release it on top of another; only legal moves.
function drawBoxes(end) {
  const { levels } = ui.info;
  const grid = el("div", { class: "grid", role: "group",
    "aria-label": (end.name === "start" ? "Start" : "Goal") + " boxes; columns left to right" });
  end.state.stacks.forEach((column, c) => {
    const canDrop = end.held !== null && end.held !== c && column.length < levels;
    const label = `Column ${c + 1}: ${column.length ? column.join(", ") + " (bottom up)" : "empty"}. ` +
      (end.held === null ? (column.length ? "Press to pick up its top box." : "") :
        end.held === c ? "Press to put the box back." :
          canDrop ? "Press to put the box here." : "Full.");
    const button = el("button", {
      type: "button", class: "column" + (end.held === c ? " holding" : canDrop ? " target" : ""),
      "aria-label": label, "data-col": c, id: `${end.name}-col-${c}`,
      onclick: () => columnPressed(end, c),
      ondragover: (e) => { if (end.held !== null) e.preventDefault(); },
      ondrop: (e) => { e.preventDefault(); columnPressed(end, c); },
    });
    for (let r = 0; r < levels; r++) {
      const box = column[r];
      const top = r === column.length - 1;
      const cell = el("span", {
        class: "cell" + (box ? "" : " empty") + (top && end.held === c ? " held" : ""),
        draggable: box && top ? "true" : null, "data-box": box || null,
        ondragstart: () => { end.held = c; },
      });
      if (box) {
        cell.style.background = BOX_COLOURS[box] || "#475467";
        cell.textContent = box[0].toUpperCase();
        cell.title = box;
      }
      button.append(cell);
    }
    grid.append(button);
  });
  end.editor.append(grid, el("p", { class: "muted", text: end.held === null ?
    "Click (or Enter on) a column to pick its top box, then a column to put it on; or drag." :
    "Now choose the column to put it on (Escape cancels)." }));
}

function columnPressed(end, c) {
  const stacks = end.state.stacks;
  if (end.held === null) {
    if (stacks[c].length) end.held = c;
    drawEditor(end);
  } else if (end.held === c) {
    end.held = null;
    drawEditor(end);
  } else if (stacks[c].length < ui.info.levels) {
    stacks[c].push(stacks[end.held].pop());
    end.held = null;
    refresh(end);
  } else {
    drawEditor(end);  // a full column takes no box: the rules stand
    return;
  }
  const again = $(`${end.name}-col-${c}`);
  if (again) again.focus();
}

function drawFolds(end) {
  const box = el("fieldset", { class: "folds" },
    el("legend", { text: ui.info.task === "cloth_folding" ? "Folded corners" : "Folds" }));
  const lockedBy = ui.info.locked_by || {};
  for (const fold of ui.info.folds) {
    // A fold whose move the rules forbid now (something folded over it) cannot be toggled.
    const held = (lockedBy[fold] || []).filter((f) => end.state.folds.includes(f));
    const input = el("input", { type: "checkbox", id: `${end.name}-fold-${fold}`, value: fold,
      checked: end.state.folds.includes(fold) ? "checked" : null,
      disabled: held.length ? "disabled" : null,
      title: held.length ? `unfold ${held.join(" and ").replaceAll("_", " ")} first` : null,
      onchange: (e) => {
        end.state.folds = ui.info.folds.filter((f) =>
          f === fold ? e.target.checked : end.state.folds.includes(f));
        refresh(end);
      } });
    box.append(el("label", {}, input, " " + fold.replace("_", " ")));
  }
  end.editor.append(box);
}

// Rope-box: two boxes on a grid (at most 2 steps apart) and the pillar the rope bends round.
function randomRopeBox() {
  const n = ui.info.grid;
  const cells = [];
  for (let r = 0; r < n; r++) for (let c = 0; c < n; c++) cells.push({ row: r, col: c });
  const any = (list) => list[Math.floor(Math.random() * list.length)];
  const green = any(cells);
  const steps = (a, b) => Math.abs(a.row - b.row) + Math.abs(a.col - b.col);
  const orange = any(cells.filter((c) => steps(c, green) >= 1 && steps(c, green) <= 2));
  const diagonal = green.row !== orange.row && green.col !== orange.col && steps(green, orange) === 2;
  // diagonal boxes have a pillar between them: the rope passes it on one side
  const pillar = { row: Math.min(green.row, orange.row), col: Math.min(green.col, orange.col) };
  const rope = diagonal ? { pillar, turn: any(["left", "right"]) } : null;
  return { boxes: { green, orange }, rope };
}

function drawRopeBox(end) {
  const n = ui.info.grid;
  const boxes = end.state.boxes;
  const at = (r, c) => Object.keys(boxes).find((b) => boxes[b].row === r && boxes[b].col === c);
  const grid = el("div", { class: "rope-grid", role: "group",
    "aria-label": (end.name === "start" ? "Start" : "Goal") + " grid; rows top down" });
  for (let r = 0; r < n; r++) {
    for (let c = 0; c < n; c++) {
      const box = at(r, c);
      const label = `Row ${r + 1}, column ${c + 1}: ${box ? box + " box" : "empty"}. ` +
        (end.held === null ? (box ? "Press to pick it up." : "") :
          box === end.held ? "Press to put it back." : box ? "Taken." : "Press to put the box here.");
      const button = el("button", {
        type: "button", id: `${end.name}-cell-${r}-${c}`, "aria-label": label,
        class: "rope-cell" + (box && box === end.held ? " holding" : "") +
          (end.held !== null && !box ? " target" : ""),
        onclick: () => ropeCellPressed(end, r, c),
      });
      if (box) {
        button.style.background = BOX_COLOURS[box] || "#475467";
        button.textContent = box[0].toUpperCase();
      }
      grid.append(button);
    }
  }
  const choice = el("select", { id: `${end.name}-rope`, "aria-label": "Where the rope runs",
    onchange: (e) => {
      end.state.rope = e.target.value ? JSON.parse(e.target.value) : null;
      refresh(end);
    } });
  choice.append(el("option", { value: "", text: "rope straight" }));
  for (const pillar of ui.info.pillars) {
    for (const turn of ["left", "right"]) {
      const rope = { pillar, turn };
      const same = end.state.rope && JSON.stringify(end.state.rope) === JSON.stringify(rope);
      choice.append(el("option", { value: JSON.stringify(rope), selected: same ? "selected" : null,
        text: `round pillar (${pillar.row},${pillar.col}), on the rope's ${turn}` }));
    }
  }
  end.editor.append(grid, el("label", {}, "Rope ", choice), el("p", { class: "muted",
    text: end.held === null ? "Click a box, then the cell to put it in." :
      "Now choose its cell (Escape cancels)." }));
}

function ropeCellPressed(end, r, c) {
  const boxes = end.state.boxes;
  const box = Object.keys(boxes).find((b) => boxes[b].row === r && boxes[b].col === c);
  if (end.held === null) {
    if (box) end.held = box;
    drawEditor(end);
  } else if (box === end.held) {
    end.held = null;
    drawEditor(end);
  } else if (!box) {
    boxes[end.held] = { row: r, col: c };
    end.held = null;
    refresh(end);  // the server names what the rules refuse (too far apart, the rope)
  }
  const again = $(`${end.name}-cell-${r}-${c}`);
  if (again) again.focus();
}

document.addEventListener("keydown", (e) => {
  if (e.key !== "Escape") return;
  for (const end of Object.values(ui.ends)) {
    if (end.held !== null) { end.held = null; drawEditor(end); }
  }
});

// --- plans --------------------------------------------------------------------------------------
function timingText(header) {
  if (!header) return "";
  const parts = header.split(",").map((m) => {
    const [name, dur] = m.trim().split(";dur=");
    return `${name} ${Number(dur).toFixed(1)} ms`;
  });
  return "Server-Timing: " + parts.join(" · ");
}

async function marksFor(actions) {
  const distinct = [...new Map(actions.filter(Boolean).map((a) => [JSON.stringify(a), a])).values()];
  const marks = new Map();
  if (!distinct.length) return { marks, size: null };
  try {
    const reply = await api("POST", "/action-pixels", { task: ui.task, actions: distinct });
    const body = await reply.json();
    distinct.forEach((a, i) => marks.set(JSON.stringify(a), body.marks[i]));
    return { marks, size: body.image_size };
  } catch (err) {
    showError(err);  // the plans are still shown, without marks
    return { marks, size: null };
  }
}

// One image with the action that leaves it drawn over it: pick (blue) and release (green).
function frame(src, alt, mark, size) {
  const img = el("img", { src, alt });
  const box = el("div", { class: "frame" }, img);
  if (mark && size) {
    const svg = svgEl("svg", { viewBox: `0 0 ${size} ${size}`, "aria-hidden": "true", class: "marks" });
    const r = size / 14;
    const [px, py] = mark.pick;
    const [rx, ry] = mark.release;
    svg.append(
      svgEl("line", { x1: px, y1: py, x2: rx, y2: ry, stroke: "#fff", "stroke-width": size / 40,
        "stroke-dasharray": `${size / 25} ${size / 40}` }),
      svgEl("circle", { cx: px, cy: py, r, fill: "none", stroke: "#1f6fe5",
        "stroke-width": size / 32, class: "pick" }),
      svgEl("circle", { cx: rx, cy: ry, r, fill: "none", stroke: "#17a34a",
        "stroke-width": size / 32, class: "release" }),
    );
    box.append(svg);
  }
  return box;
}

function nodeState(node) {  // what the node shows: its view, where the planner labels it
  const found = ui.graph && ui.graph.nodes[node];
  return found ? found.view || found.state : null;
}

// How well the model knows each end: an end it does not know gets no plan, and says so.
function showMatch(match) {
  const box = $("match");
  box.replaceChildren();
  if (!match) return;
  for (const end of ["start", "goal"]) {
    const m = match[end];
    const text = `${end[0].toUpperCase() + end.slice(1)}: ` + (m.known ? "known" : "NOT known") +
      ` (score ${m.score.toFixed(2)}, 1 at most; nearest node ${m.node})`;
    box.append(el("span", { class: m.known ? "known" : "unknown", text }));
  }
}

async function plan() {
  clearErrors();
  $("reason").textContent = "";
  showMatch(null);
  $("timing").textContent = "";
  const list = $("plan-list");
  list.replaceChildren(el("p", { class: "muted", text: "Planning…" }));
  const button = $("plan-btn");
  button.disabled = true;
  try {
    await Promise.all(Object.values(ui.ends).map((end) => end.reading));
    const maxPlans = Number($("max-plans").value);
    const reply = await api("POST", "/plan", {
      task: ui.task, start: endpointBody(ui.ends.start), goal: endpointBody(ui.ends.goal),
      max_plans: Number.isFinite(maxPlans) ? maxPlans : $("max-plans").value,
    });
    $("timing").textContent = timingText(reply.headers.get("server-timing"));
    const body = await reply.json();
    showMatch(body.match);
    ui.plans = body.plans;
    ui.selected = 0;
    list.replaceChildren();
    if (!body.plans.length) {
      $("reason").textContent = "No plan: " + (body.reason || "no reason given");
      highlightPath();
      return;
    }
    const { marks, size } = await marksFor(body.plans.flatMap((p) => p.actions));
    body.plans.forEach((p, k) => list.append(planView(p, k, marks, size)));
    highlightPath();
  } catch (err) {
    list.replaceChildren();
    showError(err);
  } finally {
    button.disabled = false;
  }
}

function planView(p, k, marks, size) {
  const head = el("h3", { text: `Plan ${k + 1}: ${p.actions.length} action` +
    (p.actions.length === 1 ? "" : "s") + (p.actions.length ? `, support ${p.support.toFixed(2)}` +
      ` (fewest training pairs behind a step: ${Math.min(...p.supports)}),` +
      ` APN confidence ${p.confidence.toFixed(3)}` : "") });
  const show = el("button", { type: "button", text: "Show on the roadmap",
    onclick: () => { ui.selected = k; highlightPath(); } });
  const strip = el("div", { class: "strip" });
  p.nodes.forEach((node, i) => {
    const action = p.actions[i];
    const mark = action ? marks.get(JSON.stringify(action)) : null;
    const src = p.images[i] ? "data:image/png;base64," + p.images[i] : "";
    const caption = el("figcaption", {},
      el("div", { text: `node ${node}` }),
      el("div", { class: "muted", text: stateText(nodeState(node)) }),
      action ? el("div", { class: "act", text: `${actionText(action)} · ${p.confidences[i].toFixed(3)}` }) :
        el("div", { class: "muted", text: i === 0 ? "start = goal" : "goal" }));
    strip.append(el("figure", {
      class: "step", "data-node": node, "data-action": action ? JSON.stringify(action) : null,
    }, frame(src, `plan ${k + 1}, step ${i + 1}: node ${node}`, mark, size), caption));
  });
  return el("div", { class: "plan" + (k === ui.selected ? " selected" : ""), "data-plan": k },
    el("div", { class: "plan-head" }, head, show), strip);
}

// --- execution, streamed -------------------------------------------------------------------------
async function execute() {
  clearErrors();
  const start = ui.ends.start;
  if (!start.state || start.image) {
    $("start-error").textContent = "Execution starts from a state in the simulator: set the " +
      "start with the editor (an uploaded image can only be planned from).";
    return;
  }
  const status = $("exec-status");
  const steps = $("exec-steps");
  // The observed start first: the first action is drawn on it once it is known.
  steps.replaceChildren(el("figure", { class: "step" },
    frame(start.preview.src, "start", null, null), el("figcaption", { text: "start" })));
  status.className = "muted";
  status.textContent = "Running in the simulator…";
  $("execute-btn").disabled = true;
  try {
    const reply = await api("POST", "/execute/stream", {
      task: ui.task, start: { state: start.state }, goal: endpointBody(ui.ends.goal), seed: 0,
    });
    await readEvents(reply, async (event, data) => {
      if (event === "step") {
        const { marks, size } = await marksFor([data.action]);
        const src = "data:image/png;base64," + data.image;
        steps.append(el("figure", { class: "step", "data-action": JSON.stringify(data.action) },
          frame(src, `after step ${data.step}`, null, size),
          el("figcaption", {}, el("div", { text: `step ${data.step}: ${actionText(data.action)}` }),
            el("div", { class: "muted", text: data.state ? stateText(data.state) : "" }))));
        const before = steps.children[steps.children.length - 2];
        if (before) markExecuted(before, marks.get(JSON.stringify(data.action)), size);
        status.textContent = `Running in the simulator… ${data.step} step${data.step === 1 ? "" : "s"} done`;
      } else if (event === "done") {
        status.className = data.success ? "success" : "failure";
        status.textContent = data.success ?
          `Success: the simulator reached the goal in ${data.steps} step${data.steps === 1 ? "" : "s"}.` :
          `Failure: the goal was not reached (${data.detail || data.reason}) after ` +
          `${data.steps} steps; final state ${stateText(data.final_view || data.final_state)}.`;
      } else if (event === "error") {
        status.className = "failure";
        status.textContent = "Execution stopped.";
        showError(new ApiError(data.status, data.detail));
      }
    });
  } catch (err) {
    status.className = "failure";
    status.textContent = "Execution failed.";
    showError(err);
  } finally {
    $("execute-btn").disabled = false;
  }
}

// The action taken from an observed image is drawn on that image once it is known.
function markExecuted(figure, mark, size) {
  const box = figure.querySelector(".frame");
  if (!box || !mark) return;
  const img = box.querySelector("img");
  box.replaceWith(frame(img.src, img.alt, mark, size));
}

async function readEvents(reply, handle) {
  const reader = reply.body.getReader();
  const decoder = new TextDecoder();
  let buffer = "";
  for (;;) {
    const { value, done } = await reader.read();
    if (done) break;
    buffer += decoder.decode(value, { stream: true });
    let cut;
    while ((cut = buffer.indexOf("\n\n")) >= 0) {
      const block = buffer.slice(0, cut);
      buffer = buffer.slice(cut + 2);
      let event = "message";
      let data = "";
      for (const line of block.split("\n")) {
        if (line.startsWith("event: ")) event = line.slice(7);
        else if (line.startsWith("data: ")) data += line.slice(6);
      }
      await handle(event, data ? JSON.parse(data) : null);
    }
  }
}

// --- health, live ----------------------------------------------------------------------------------
async function pollHealth() {
  const pill = $("health-status");
  const list = $("health-services");
  const controller = new AbortController();
  const timer = setTimeout(() => controller.abort(), 4000);
  try {
    const reply = await fetch("/health", { signal: controller.signal, headers: headers(false) });
    const body = await reply.json();
    pill.className = "pill " + (body.status === "ok" ? "ok" : "down");
    pill.textContent = body.status === "ok" ? "all services up" :
      body.status === "inconsistent" ? "services serve different models" : (body.detail || "unavailable");
    list.replaceChildren(...Object.entries(body.services).map(([name, s]) => {
      const perTask = new Map();  // task -> [replicas, model ids, roadmap versions]
      for (const i of s.instances) {
        const [count, models, versions] = perTask.get(i.task) || [0, new Set(), new Set()];
        if (i.roadmap_version) versions.add(i.roadmap_version);
        perTask.set(i.task, [count + 1, models.add(i.model_id.slice(0, 8)), versions]);
      }
      const tasks = [...perTask].map(([task, [count, models, versions]]) =>
        `${task} ×${count} (model ${[...models].join("/")}` +
        (versions.size ? `, roadmap ${[...versions].join("/")})` : ")"));
      const text = `${name} ${s.status === "ok" ? "up" : "DOWN"}` +
        (tasks.length ? ": " + tasks.join(", ") : ": no replica");
      return el("li", { class: s.status === "ok" ? "" : "down", text, "data-service": name });
    }));
    const planners = (body.services.planner?.instances || []).filter((i) => i.task === ui.task);
    followRoadmap(new Set(planners.map((i) => i.roadmap_version).filter(Boolean)));
  } catch (err) {
    pill.className = "pill down";
    pill.textContent = "gateway unreachable";
    list.replaceChildren();
  } finally {
    clearTimeout(timer);
    ui.healthTimer = setTimeout(pollHealth, 2000);
  }
}

// A growing roadmap: once no planner of this task serves the version drawn, draw the new one
// (and try again after a load that failed, say during the switch).
function followRoadmap(versions) {
  if (!ui.task || ui.roadmapLoading || !versions || !versions.size) return;
  const drawn = ui.graph?.roadmap_version;
  if (ui.graph ? !drawn || versions.has(drawn) : !ui.roadmapRetry) return;
  nodeImages.clear();  // a grown node's id may stand for another image in another version
  loadRoadmap();
}

// --- the roadmap picture -----------------------------------------------------------------------------
const view = { x: 0, y: 0, w: 1000, h: 700 };
const nodeImages = new Map();

function setView() {
  $("roadmap-svg").setAttribute("viewBox", `${view.x} ${view.y} ${view.w} ${view.h}`);
}
function zoom(factor, cx = view.x + view.w / 2, cy = view.y + view.h / 2) {
  view.x = cx - (cx - view.x) * factor;
  view.y = cy - (cy - view.y) * factor;
  view.w *= factor;
  view.h *= factor;
  setView();
}

async function loadRoadmap() {
  const svg = $("roadmap-svg");
  svg.replaceChildren();
  ui.graph = null;
  $("roadmap-info").textContent = "Loading the roadmap…";
  const load = ++ui.roadmapLoads;  // a later load (another task, say) supersedes this one
  ui.roadmapLoading = true;
  try {
    const reply = await api("GET", `/tasks/${encodeURIComponent(ui.task)}/roadmap`);
    const graph = await reply.json();
    if (load !== ui.roadmapLoads) return;
    ui.graph = graph;
  } catch (err) {
    if (load !== ui.roadmapLoads) return;
    ui.roadmapRetry = ![401, 403, 404].includes(err.status);  // a key or a task: no retry
    $("roadmap-info").textContent = "";
    showError(err, "task-error");
    return;
  } finally {
    if (load === ui.roadmapLoads) ui.roadmapLoading = false;
  }
  const g = ui.graph;
  const known = g.nodes.filter((n) => n.state).length;
  const twinLinks = g.twins ?? [];
  const twins = twinLinks.length ? `, ${twinLinks.length} twin links (dashed)` : "";
  const version = g.roadmap_version ? `, roadmap ${g.roadmap_version}` : "";
  $("roadmap-info").textContent = `${g.nodes.length} nodes, ${g.edges.length} edges${twins} (model ` +
    `${g.model_id.slice(0, 8)}${version}; layout: ${g.layout}; ${known} nodes with a known state).`;
  Object.assign(view, { x: 0, y: 0, w: 1000, h: 700 });
  setView();
  const pos = (n) => [g.nodes[n].x * 1000, g.nodes[n].y * 700];
  const edges = svgEl("g", { class: "edges" });
  for (const [a, b, w] of g.edges) {
    const [x1, y1] = pos(a);
    const [x2, y2] = pos(b);
    edges.append(svgEl("line", { x1, y1, x2, y2, class: "edge", "data-step": stepKey(a, b),
      "stroke-opacity": Math.min(1, 0.3 + w / 20) }));
  }
  for (const [a, b] of twinLinks) {  // one state seen as two nodes
    const [x1, y1] = pos(a);
    const [x2, y2] = pos(b);
    edges.append(svgEl("line", { x1, y1, x2, y2, class: "twin" }));
  }
  const nodes = svgEl("g", { class: "nodes" });
  for (const n of g.nodes) {
    const [cx, cy] = pos(n.id);
    const dot = svgEl("circle", { cx, cy, r: 5, class: "node", "data-node": n.id });
    dot.addEventListener("mouseenter", (e) => showNode(n.id, e));
    dot.addEventListener("mouseleave", hideNode);
    nodes.append(dot);
  }
  svg.append(edges, nodes);
  highlightPath();
}

async function nodeImage(id) {
  if (!nodeImages.has(id)) {
    nodeImages.set(id, api("GET", `/tasks/${encodeURIComponent(ui.task)}/roadmap/nodes/${id}.png`)
      .then((r) => r.blob()).then((b) => URL.createObjectURL(b))
      .catch((err) => { nodeImages.delete(id); throw err; }));
  }
  return nodeImages.get(id);
}

async function showNode(id, event) {
  const tip = $("node-tip");
  const node = ui.graph.nodes[id];
  const img = el("img", { alt: `decoded image of node ${id}` });
  tip.replaceChildren(img, el("div", { text: `node ${id}: ${stateText(node.view || node.state)}` +
    (node.purity !== null ? ` (purity ${node.purity.toFixed(2)})` : "") }));
  const area = $("roadmap-view").getBoundingClientRect();
  let x = 12;
  let y = 12;
  if (event && event.clientX !== undefined) {
    x = Math.min(event.clientX - area.left + 14, area.width - 210);
    y = Math.max(event.clientY - area.top - 120, 0);
  }
  tip.style.left = x + "px";
  tip.style.top = y + "px";
  tip.hidden = false;
  tip.dataset.node = id;
  try {
    const url = await nodeImage(id);
    if (tip.dataset.node === String(id)) img.src = url;
  } catch (err) {
    tip.append(el("div", { class: "error", text: "image unavailable: " + err.message }));
  }
}
function hideNode() { $("node-tip").hidden = true; }

// A plan steps between twin groups (nodes of one state) along any edge that joins them.
function stepKey(a, b) {
  // a node the loaded graph lacks (the roadmap grew since) or an older gateway: its own id
  const group = (n) => ui.graph?.nodes[n]?.group ?? n;
  const [x, y] = [group(a), group(b)].sort((p, q) => p - q);
  return `${x}-${y}`;
}

function highlightPath() {
  const svg = $("roadmap-svg");
  for (const node of svg.querySelectorAll(".on, .end")) node.classList.remove("on", "end");
  for (const p of document.querySelectorAll(".plan")) {
    p.classList.toggle("selected", Number(p.dataset.plan) === ui.selected);
  }
  const holder = $("path-nodes");
  holder.replaceChildren();
  const chosen = ui.plans[ui.selected];
  if (!chosen || !ui.graph) return;
  const nodes = chosen.nodes;
  nodes.forEach((n, i) => {
    const dot = svg.querySelector(`[data-node="${n}"]`);
    if (dot) {
      dot.classList.add(i === 0 || i === nodes.length - 1 ? "end" : "on");
      dot.parentNode.append(dot);  // drawn on top
    }
    if (i > 0) {  // every edge between the two nodes' twin groups
      for (const line of svg.querySelectorAll(`[data-step="${stepKey(nodes[i - 1], n)}"]`)) {
        line.classList.add("on");
        line.parentNode.append(line);
      }
    }
    holder.append(el("button", { type: "button", class: "path-node", text: `node ${n}`,
      onfocus: () => showNode(n), onblur: hideNode, onmouseenter: () => showNode(n),
      onmouseleave: hideNode }));
  });
  holder.prepend(el("span", { class: "muted", text: `Plan ${ui.selected + 1} on the roadmap: ` }));
}

function roadmapKeys(e) {
  const step = view.w / 10;
  const moves = { ArrowLeft: [-step, 0], ArrowRight: [step, 0], ArrowUp: [0, -step], ArrowDown: [0, step] };
  if (moves[e.key]) {
    view.x += moves[e.key][0];
    view.y += moves[e.key][1];
    setView();
  } else if (e.key === "+" || e.key === "=") zoom(0.8);
  else if (e.key === "-") zoom(1.25);
  else return;
  e.preventDefault();
}

// --- start-up ------------------------------------------------------------------------------------------
async function chooseTask(task) {
  ui.task = task;
  ui.plans = [];
  nodeImages.clear();
  $("plan-list").replaceChildren();
  $("reason").textContent = "";
  showMatch(null);
  $("timing").textContent = "";
  $("exec-steps").replaceChildren();
  $("exec-status").textContent = "Not run yet.";
  clearErrors();
  try {
    const info = await (await api("GET", `/tasks/${encodeURIComponent(task)}`)).json();
    if (ui.task !== task) return;  // another task was chosen meanwhile: its editors stand
    ui.info = info;
  } catch (err) {
    if (ui.task === task) showError(err, "task-error");
    return;
  }
  buildEndpoint("start");
  buildEndpoint("goal");
  await loadRoadmap();
}

async function main() {
  const key = $("api-key");
  key.value = sessionStorage.getItem("lsr-api-key") || "";
  key.addEventListener("change", () => {
    sessionStorage.setItem("lsr-api-key", key.value.trim());
    if (ui.task) chooseTask(ui.task); else start();
  });
  $("plan-btn").addEventListener("click", plan);
  $("execute-btn").addEventListener("click", execute);
  $("task").addEventListener("change", (e) => chooseTask(e.target.value));
  $("zoom-in").addEventListener("click", () => zoom(0.8));
  $("zoom-out").addEventListener("click", () => zoom(1.25));
  $("zoom-reset").addEventListener("click", () => { Object.assign(view, { x: 0, y: 0, w: 1000, h: 700 }); setView(); });
  const svg = $("roadmap-svg");
  svg.addEventListener("keydown", roadmapKeys);
  svg.addEventListener("wheel", (e) => {
    e.preventDefault();
    const box = svg.getBoundingClientRect();
    const cx = view.x + ((e.clientX - box.left) / box.width) * view.w;
    const cy = view.y + ((e.clientY - box.top) / box.height) * view.h;
    zoom(e.deltaY < 0 ? 0.85 : 1 / 0.85, cx, cy);
  }, { passive: false });
  pollHealth();
  await start();
}

async function start() {
  let tasks;
  try {
    tasks = (await (await api("GET", "/tasks")).json()).tasks;
  } catch (err) {
    showError(err, "task-error");
    return;
  }
  const select = $("task");
  select.replaceChildren(...tasks.map((t) => el("option", { value: t, text: t.replace("_", " ") })));
  await chooseTask(tasks[0]);
  document.body.dataset.ready = "true";
}

main();
