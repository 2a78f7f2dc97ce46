// The crop page: draw, move and resize a left and a right box (mouse or touch), with zoom.
// Boxes are kept in ORIGINAL image pixels (the image shown may be a smaller preview).
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const cfg = root.dataset;
  const preview = cfg.preview === "true";
  const minBox = Number(cfg.minBox || 16);
  const stage = document.getElementById("crop-stage");
  const image = document.getElementById("card-image");
  const status = document.getElementById("status");
  const errorBox = document.getElementById("error");
  const coords = document.getElementById("coords");
  const submitButton = document.getElementById("submit-answer");
  const answered = document.getElementById("answered");
  const help = document.getElementById("help");
  const HELP_SEEN = "keystone-crowd-crop-help-seen";
  const boxEls = { left: stage.querySelector(".box-left"), right: stage.querySelector(".box-right") };

  let queue = [], shown = null, busy = false, zoom = 1, active = "left", drag = null;
  let boxes = { left: null, right: null };  // [x0, y0, x1, y1] in original pixels
  const keys = new Map();

  const say = (t) => { status.textContent = t; };
  const fail = (t) => { errorBox.textContent = t; errorBox.hidden = false; };
  const clearError = () => { errorBox.hidden = true; };
  const newKey = () => (window.crypto && crypto.randomUUID) ? crypto.randomUUID()
    : Date.now().toString(36) + Math.random().toString(36).slice(2);
  const task = () => queue[0];
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

  async function api(url, body) {
    const response = await fetch(url, {
      method: "POST", credentials: "omit", body: JSON.stringify(body || {}),
      headers: { "Content-Type": "application/json", "X-Crowd-Token": cfg.workerToken },
    });
    let data = {};
    try { data = await response.json(); } catch (e) { /* not JSON */ }
    if (!response.ok) {
      const err = new Error((data.error && data.error.message) || ("The server answered " + response.status));
      err.status = response.status;
      throw err;
    }
    return data;
  }

  function toOriginal(event) {
    const rect = image.getBoundingClientRect();
    const t = task();
    return [clamp((event.clientX - rect.left) / rect.width, 0, 1) * t.card_width,
            clamp((event.clientY - rect.top) / rect.height, 0, 1) * t.card_height];
  }

  function select(half) {
    active = half;
    document.querySelectorAll(".half-button").forEach(b => b.setAttribute("aria-pressed", String(b.dataset.half === half)));
    for (const h in boxEls) boxEls[h].classList.toggle("selected", h === half);
  }

  function render() {
    const t = task();
    for (const half of ["left", "right"]) {
      const el = boxEls[half], b = boxes[half];
      if (!b || !t) { el.hidden = true; continue; }
      el.hidden = false;
      el.style.left = (100 * b[0] / t.card_width) + "%";
      el.style.top = (100 * b[1] / t.card_height) + "%";
      el.style.width = (100 * (b[2] - b[0]) / t.card_width) + "%";
      el.style.height = (100 * (b[3] - b[1]) / t.card_height) + "%";
    }
    const b = boxes[active];
    coords.textContent = b ? active + ": " + b.map(v => Math.round(v)).join(", ") + " px" : "";
  }

  function setZoom(z) { zoom = clamp(z, 0.5, 4); stage.style.width = (zoom * 100) + "%"; }

  function normalise(b) {
    return [Math.min(b[0], b[2]), Math.min(b[1], b[3]), Math.max(b[0], b[2]), Math.max(b[1], b[3])];
  }

  stage.addEventListener("pointerdown", (event) => {
    if (!task() || preview) return;
    event.preventDefault();
    stage.setPointerCapture(event.pointerId);
    const [x, y] = toOriginal(event);
    const boxEl = event.target.closest(".box");
    if (boxEl) {
      select(boxEl.dataset.half);
      const mode = event.target.classList.contains("tl") ? "tl" : event.target.classList.contains("br") ? "br" : "move";
      drag = { mode, half: active, start: [x, y], original: boxes[active].slice() };
    } else {
      drag = { mode: "draw", half: active, start: [x, y] };
      boxes[active] = [x, y, x, y];
    }
    render();
  });

  stage.addEventListener("pointermove", (event) => {
    if (!drag) return;
    const t = task();
    const [x, y] = toOriginal(event);
    const b = drag.original;
    if (drag.mode === "draw") boxes[drag.half] = normalise([drag.start[0], drag.start[1], x, y]);
    else if (drag.mode === "tl") boxes[drag.half] = normalise([x, y, b[2], b[3]]);
    else if (drag.mode === "br") boxes[drag.half] = normalise([b[0], b[1], x, y]);
    else {
      const dx = clamp(x - drag.start[0], -b[0], t.card_width - b[2]);
      const dy = clamp(y - drag.start[1], -b[1], t.card_height - b[3]);
      boxes[drag.half] = [b[0] + dx, b[1] + dy, b[2] + dx, b[3] + dy];
    }
    render();
  });

  function endDrag() {
    if (!drag) return;
    const half = drag.half, b = boxes[half];
    drag = null;
    if (b && (b[2] - b[0] < minBox || b[3] - b[1] < minBox)) {
      fail("The " + half + " box is smaller than " + minBox + " x " + minBox + " pixels; draw it larger.");
    } else {
      clearError();
      if (half === "left" && !boxes.right) select("right");
    }
    render();
  }
  stage.addEventListener("pointerup", endDrag);
  stage.addEventListener("pointercancel", endDrag);

  function show() {
    const t = task();
    if (!t) { image.hidden = true; shown = null; return; }
    shown = t.token;
    boxes = { left: null, right: null };
    image.src = t.image_url;
    image.hidden = false;
    if (queue[1]) { const next = new Image(); next.src = queue[1].image_url; }
    select("left");
    render();
    say("Card " + (Number(answered.textContent) + 1) + ": draw the left box, then the right box.");
    submitButton.disabled = false;
  }

  function finished(reason) {
    image.hidden = true; submitButton.disabled = true; render();
    say(reason === "all_reserved" ? "Other people hold the remaining cards; try again in a few minutes."
      : "No more cards for you right now. Thank you!");
    if (cfg.provider === "prolific" && cfg.finishUrl && reason !== "all_reserved") window.location.assign(cfg.finishUrl);
  }

  async function fetchTasks() {
    const data = await api(cfg.nextUrl, { kind: "crop" });
    answered.textContent = data.answered;
    const known = new Set(queue.map(t => t.token));
    for (const t of data.tasks) if (!known.has(t.token)) queue.push(t);
    if (queue.length) { if (shown !== queue[0].token) show(); } else finished(data.reason);
  }

  function postToMTurk(post) {
    const out = document.createElement("form");
    out.method = "POST"; out.action = post.url;
    for (const [name, value] of Object.entries(post.fields)) {
      const input = document.createElement("input");
      input.type = "hidden"; input.name = name; input.value = value; out.appendChild(input);
    }
    document.body.appendChild(out); out.submit();
  }

  async function submitAnswer() {
    if (preview || busy || !task()) return;
    if (!boxes.left || !boxes.right) { fail("Draw both boxes first: one on the left photo and one on the right."); return; }
    busy = true; submitButton.disabled = true; clearError();
    const t = task();
    if (!keys.has(t.token)) keys.set(t.token, newKey());
    const round = (b) => b.map(v => Math.round(v * 10) / 10);
    try {
      const data = await api(cfg.submitUrl, { token: t.token, key: keys.get(t.token),
                                              answer: { left: round(boxes.left), right: round(boxes.right) } });
      answered.textContent = data.answered;
      queue.shift();
      if (data.finish && data.finish.post) { postToMTurk(data.finish.post); return; }
      if (queue.length) {
        // The preloaded next card is on screen: go on at once, top the queue up meanwhile.
        show();
        busy = false;
        fetchTasks().catch(err => fail(err.message));
        return;
      }
      await fetchTasks();
    } catch (err) {
      fail(err.message);  // refusals (box outside, inverted, too small) keep the boxes for fixing
      if (err.status === 409 || err.status === 403 || err.status === 404) { queue.shift(); await fetchTasks().catch(e => fail(e.message)); }
      else submitButton.disabled = false;
    } finally { busy = false; }
  }

  async function undo() {
    if (preview || busy) return;
    busy = true; clearError();
    try {
      const data = await api(cfg.undoUrl, {});
      answered.textContent = data.answered;
      queue = [data.task].concat(queue.filter(t => t.token !== data.task.token));
      keys.delete(data.task.token);
      show();
      say("Undone: crop this card again.");
    } catch (err) { fail(err.message); } finally { busy = false; }
  }

  document.getElementById("crop-form").addEventListener("submit", (e) => { e.preventDefault(); submitAnswer(); });
  document.getElementById("undo").addEventListener("click", undo);
  document.getElementById("zoom-in").addEventListener("click", () => setZoom(zoom * 1.25));
  document.getElementById("zoom-out").addEventListener("click", () => setZoom(zoom / 1.25));
  document.getElementById("show-help").addEventListener("click", () => help.showModal());
  document.querySelectorAll(".half-button").forEach(b => b.addEventListener("click", () => { select(b.dataset.half); render(); }));
  help.addEventListener("close", () => { try { localStorage.setItem(HELP_SEEN, "1"); } catch (e) { /* blocked */ } });

  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || help.open) return;
    const key = event.key.toLowerCase();
    if (key === "enter") { event.preventDefault(); submitAnswer(); }
    else if (key === "u") { event.preventDefault(); undo(); }
    else if (key === "l" || key === "r") { select(key === "l" ? "left" : "right"); render(); }
    else if (key === "+" || key === "=") setZoom(zoom * 1.25);
    else if (key === "-") setZoom(zoom / 1.25);
    else if (key === "delete" || key === "backspace") { boxes[active] = null; render(); }
    else if (key === "h" || key === "?") help.showModal();
  });

  let seen = false;
  try { seen = localStorage.getItem(HELP_SEEN) === "1"; } catch (e) { /* blocked */ }
  if (!seen && typeof help.showModal === "function") help.showModal();
  select("left");
  if (!preview) fetchTasks().catch(err => fail(err.message));
})();
