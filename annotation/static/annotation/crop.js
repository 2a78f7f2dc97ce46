// The crop page: a left and a right box, proposed by the server (the photo areas it found), that
// the annotator moves and resizes; or draws again by dragging outside the boxes.
// Boxes are kept in ORIGINAL image pixels (the image shown may be a smaller preview).
// Fingers: one finger draws, moves and resizes (44 px corner handles); two fingers pinch to
// zoom and pan (any edit the first finger began is put back). On-screen Delete box and Undo
// edit do what Delete and Z do on a keyboard; arrow keys move the selected box, Shift+arrows
// resize it, Alt makes either ten times larger.
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const cfg = root.dataset;
  const minBox = Number(cfg.minBox || 16);
  const viewport = document.getElementById("crop-viewport");
  const stage = document.getElementById("crop-stage");
  const image = document.getElementById("card-image");
  const coords = document.getElementById("coords");
  const undoEdit = document.getElementById("undo-edit");
  const boxEls = { left: stage.querySelector(".box-left"), right: stage.querySelector(".box-right") };
  const HALVES = ["left", "right"];

  let zoom = 1, active = "left", drag = null, pinch = null;
  let boxes = { left: null, right: null };  // [x0, y0, x1, y1] in original pixels
  let history = [];  // earlier states of `boxes`, for Undo edit
  const pointers = new Map();  // pointerId -> {x, y} (client px)
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));
  const round = (b) => b.map(v => Math.round(v * 10) / 10);
  const copy = (b) => ({ left: b.left && b.left.slice(), right: b.right && b.right.slice() });

  const client = window.KeystoneTasks.create(root, {
    kind: "crop",
    undoneText: "Undone: crop this card again.",
    cardText: (n, total) => "Card " + n + (total ? " of " + total : "") + ": fit each box to its photo.",
    show(task) {
      const p = task.proposed;
      boxes = p ? { left: p.left.slice(), right: p.right.slice() } : { left: null, right: null };
      history = [];
      image.onload = fit;
      image.src = task.image_url;
      image.hidden = false;
      select(p ? "left" : "left");
      render();
    },
    restore(answer) {
      // An undone answer: its boxes, as sent, to correct (Undo edit goes back to the proposal).
      if (!Array.isArray(answer.left) || !Array.isArray(answer.right)) return;
      remember();
      boxes = { left: answer.left.slice(), right: answer.right.slice() };
      render();
    },
    showPreview() {},
    hide() { image.hidden = true; boxes = { left: null, right: null }; render(); },
    answer() {
      if (!boxes.left || !boxes.right) throw new Error("Both boxes are needed: one on the left photo and one on the right.");
      for (const half of HALVES) {
        const b = boxes[half];
        if (b[2] - b[0] < minBox || b[3] - b[1] < minBox) {
          select(half); render();
          throw new Error("The " + half + " box is smaller than " + minBox + " x " + minBox + " pixels; make it larger.");
        }
      }
      return { left: round(boxes.left), right: round(boxes.right) };
    },
  });
  const task = client.current;
  const preview = client.preview;
  const fail = client.fail, clearError = client.clearError;
  const help = window.KeystoneTasks.instructions(document.getElementById("help"), "keystone-crowd-crop-help-seen");

  // The stage at zoom 1 fills the viewport's width but never more height than the window leaves.
  function baseWidth() {
    const t = task();
    const aspect = t ? t.card_width / t.card_height : 2;
    const top = viewport.getBoundingClientRect().top + window.scrollY;
    const below = document.getElementById("crop-form").offsetHeight + 24;
    const room = Math.max(160, window.innerHeight - Math.min(top, 0.5 * window.innerHeight) - below);
    const style = getComputedStyle(viewport);
    const inner = viewport.clientWidth - parseFloat(style.paddingLeft) - parseFloat(style.paddingRight);
    const innerRoom = room - parseFloat(style.paddingTop) - parseFloat(style.paddingBottom);
    return Math.min(inner, innerRoom * aspect);
  }
  function fit() { setZoom(zoom); }
  window.addEventListener("resize", fit);

  function setZoom(z, anchor) {
    const before = stage.getBoundingClientRect();
    zoom = clamp(z, 1, 6);
    stage.style.width = Math.round(baseWidth() * zoom) + "px";
    if (anchor) {
      // Keep the card point under the fingers (or the view's centre) where it was.
      const rect = viewport.getBoundingClientRect();
      const width = stage.getBoundingClientRect().width;
      viewport.scrollLeft = anchor.fx * width - (anchor.x - rect.left);
      viewport.scrollTop = anchor.fy * width * (before.height / Math.max(1, before.width)) - (anchor.y - rect.top);
    }
  }
  function centreAnchor() {
    const rect = viewport.getBoundingClientRect(), s = stage.getBoundingClientRect();
    const x = rect.left + rect.width / 2, y = rect.top + rect.height / 2;
    return { x, y, fx: (x - s.left) / s.width, fy: (y - s.top) / s.width };
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
    for (const half of HALVES) {
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
    undoEdit.disabled = history.length === 0;
  }

  function remember() { history.push(copy(boxes)); if (history.length > 50) history.shift(); }
  function undoLastEdit() { if (!history.length) return; boxes = history.pop(); keyRun = null; render(); clearError(); }
  function deleteBox() { if (!boxes[active]) return; remember(); boxes[active] = null; render(); }

  function normalise(b) {
    return [Math.min(b[0], b[2]), Math.min(b[1], b[3]), Math.max(b[0], b[2]), Math.max(b[1], b[3])];
  }

  // Which photo a point on the card belongs to: the side of the gap between the two boxes (or
  // of the card's middle), so drawing on the right photo always edits the right box.
  function halfAt(x) {
    const t = task();
    let middle = t.card_width / 2;
    if (boxes.left && boxes.right) middle = (boxes.left[2] + boxes.right[0]) / 2;
    else if (t.proposed) middle = (t.proposed.left[2] + t.proposed.right[0]) / 2;
    return x < middle ? "left" : "right";
  }

  const fingerDistance = () => { const [a, b] = [...pointers.values()]; return Math.hypot(a.x - b.x, a.y - b.y); };
  const fingerMiddle = () => { const [a, b] = [...pointers.values()]; return { x: (a.x + b.x) / 2, y: (a.y + b.y) / 2 }; };

  stage.addEventListener("pointerdown", (event) => {
    if (!task() || preview) return;
    event.preventDefault();
    stage.setPointerCapture(event.pointerId);
    pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
    if (pointers.size === 2) {
      // A second finger: this is a pinch or a pan, not an edit. Put back what the first began.
      if (drag) { boxes = drag.before; history.pop(); drag = null; render(); }
      const mid = fingerMiddle(), s = stage.getBoundingClientRect();
      pinch = { distance: fingerDistance(), zoom, fx: (mid.x - s.left) / s.width, fy: (mid.y - s.top) / s.width };
      return;
    }
    if (pointers.size > 2 || pinch) return;
    const [x, y] = toOriginal(event);
    const boxEl = event.target.closest(".box");
    remember();
    const before = history[history.length - 1];
    if (boxEl) {
      select(boxEl.dataset.half);
      const corner = event.target.dataset.corner;
      drag = { mode: corner || "move", half: active, start: [x, y], original: boxes[active].slice(), before };
    } else {
      select(halfAt(x));
      drag = { mode: "draw", half: active, start: [x, y], before };
      boxes[active] = [x, y, x, y];
    }
    render();
  });

  stage.addEventListener("pointermove", (event) => {
    if (!pointers.has(event.pointerId)) return;
    pointers.set(event.pointerId, { x: event.clientX, y: event.clientY });
    if (pinch) {
      if (pointers.size < 2) return;
      const mid = fingerMiddle();
      setZoom(pinch.zoom * fingerDistance() / Math.max(1, pinch.distance), { x: mid.x, y: mid.y, fx: pinch.fx, fy: pinch.fy });
      return;
    }
    if (!drag) return;
    const t = task();
    const [x, y] = toOriginal(event);
    const b = drag.original;
    if (drag.mode === "draw") boxes[drag.half] = normalise([drag.start[0], drag.start[1], x, y]);
    else if (drag.mode === "tl") boxes[drag.half] = normalise([x, y, b[2], b[3]]);
    else if (drag.mode === "tr") boxes[drag.half] = normalise([b[0], y, x, b[3]]);
    else if (drag.mode === "bl") boxes[drag.half] = normalise([x, b[1], b[2], y]);
    else if (drag.mode === "br") boxes[drag.half] = normalise([b[0], b[1], x, y]);
    else {
      const dx = clamp(x - drag.start[0], -b[0], t.card_width - b[2]);
      const dy = clamp(y - drag.start[1], -b[1], t.card_height - b[3]);
      boxes[drag.half] = [b[0] + dx, b[1] + dy, b[2] + dx, b[3] + dy];
    }
    render();
  });

  function endPointer(event) {
    pointers.delete(event.pointerId);
    if (pinch) { if (pointers.size === 0) pinch = null; return; }
    if (!drag) return;
    const half = drag.half, b = boxes[half];
    const unchanged = JSON.stringify(drag.before) === JSON.stringify(boxes);
    drag = null;
    if (unchanged) history.pop();
    if (b && (b[2] - b[0] < minBox || b[3] - b[1] < minBox)) {
      fail("The " + half + " box is smaller than " + minBox + " x " + minBox + " pixels; draw it larger.");
    } else {
      clearError();
      if (half === "left" && !boxes.right) select("right");
    }
    render();
  }
  stage.addEventListener("pointerup", endPointer);
  stage.addEventListener("pointercancel", endPointer);

  document.getElementById("crop-form").addEventListener("submit", (e) => { e.preventDefault(); client.submit(); });
  document.getElementById("undo").addEventListener("click", client.undo);
  document.getElementById("zoom-in").addEventListener("click", () => setZoom(zoom * 1.25, centreAnchor()));
  document.getElementById("zoom-out").addEventListener("click", () => setZoom(zoom / 1.25, centreAnchor()));
  document.getElementById("delete-box").addEventListener("click", deleteBox);
  undoEdit.addEventListener("click", undoLastEdit);
  document.getElementById("show-help").addEventListener("click", help.open);
  document.querySelectorAll(".half-button").forEach(b => b.addEventListener("click", () => { select(b.dataset.half); render(); }));

  // Arrow keys: move the selected box by one screen pixel's worth of the card (Alt: ten), or
  // with Shift resize it by its right and bottom edges. A run of presses is one Undo edit step.
  const ARROWS = { arrowleft: [-1, 0], arrowright: [1, 0], arrowup: [0, -1], arrowdown: [0, 1] };
  let keyRun = null;
  function nudge(event) {
    const t = task(), b = boxes[active];
    if (!t || !b || preview) return false;
    const [dx, dy] = ARROWS[event.key.toLowerCase()];
    const rect = image.getBoundingClientRect();
    const step = (event.altKey ? 10 : 1) * t.card_width / Math.max(1, rect.width);  // original px per screen px
    if (keyRun !== active) { remember(); keyRun = active; }
    if (event.shiftKey) {
      const x1 = clamp(b[2] + dx * step, b[0] + minBox, t.card_width);
      const y1 = clamp(b[3] + dy * step, b[1] + minBox, t.card_height);
      boxes[active] = [b[0], b[1], x1, y1];
    } else {
      const mx = clamp(dx * step, -b[0], t.card_width - b[2]);
      const my = clamp(dy * step, -b[1], t.card_height - b[3]);
      boxes[active] = [b[0] + mx, b[1] + my, b[2] + mx, b[3] + my];
    }
    clearError();
    render();
    return true;
  }
  document.addEventListener("keyup", (event) => { if (!(event.key.toLowerCase() in ARROWS)) keyRun = null; });
  stage.addEventListener("pointerdown", () => { keyRun = null; });

  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || help.isOpen()) return;
    const key = event.key.toLowerCase();
    if (key in ARROWS) {
      const target = event.target;
      if (target && ["INPUT", "SELECT", "TEXTAREA"].includes(target.tagName)) return;
      if (nudge(event)) event.preventDefault();
      return;
    }
    if (event.altKey) return;
    if (key === "enter") { event.preventDefault(); client.submit(); }
    else if (key === "u") { event.preventDefault(); client.undo(); }
    else if (key === "z") { event.preventDefault(); undoLastEdit(); }
    else if (key === "l" || key === "r") { select(key === "l" ? "left" : "right"); keyRun = null; render(); }
    else if (key === "+" || key === "=") setZoom(zoom * 1.25, centreAnchor());
    else if (key === "-") setZoom(zoom / 1.25, centreAnchor());
    else if (key === "delete" || key === "backspace") deleteBox();
    else if (key === "h" || key === "?") help.open();
  });
  fit();
  client.start();
})();
