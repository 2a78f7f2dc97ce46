// The crop page: draw, move and resize a left and a right box (mouse or touch), with zoom.
// Boxes are kept in ORIGINAL image pixels (the image shown may be a smaller preview).
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const cfg = root.dataset;
  const minBox = Number(cfg.minBox || 16);
  const stage = document.getElementById("crop-stage");
  const image = document.getElementById("card-image");
  const coords = document.getElementById("coords");
  const boxEls = { left: stage.querySelector(".box-left"), right: stage.querySelector(".box-right") };

  let zoom = 1, active = "left", drag = null;
  let boxes = { left: null, right: null };  // [x0, y0, x1, y1] in original pixels
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));
  const round = (b) => b.map(v => Math.round(v * 10) / 10);

  const client = window.KeystoneTasks.create(root, {
    kind: "crop",
    undoneText: "Undone: crop this card again.",
    cardText: (n) => "Card " + n + ": draw the left box, then the right box.",
    show(task) {
      boxes = { left: null, right: null };
      image.src = task.image_url;
      image.hidden = false;
      select("left");
      render();
    },
    hide() { image.hidden = true; render(); },
    answer() {
      if (!boxes.left || !boxes.right) throw new Error("Draw both boxes first: one on the left photo and one on the right.");
      return { left: round(boxes.left), right: round(boxes.right) };
    },
  });
  const task = client.current;
  const preview = client.preview;
  const fail = client.fail, clearError = client.clearError;
  const help = window.KeystoneTasks.instructions(document.getElementById("help"), "keystone-crowd-crop-help-seen");

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

  document.getElementById("crop-form").addEventListener("submit", (e) => { e.preventDefault(); client.submit(); });
  document.getElementById("undo").addEventListener("click", client.undo);
  document.getElementById("zoom-in").addEventListener("click", () => setZoom(zoom * 1.25));
  document.getElementById("zoom-out").addEventListener("click", () => setZoom(zoom / 1.25));
  document.getElementById("show-help").addEventListener("click", help.open);
  document.querySelectorAll(".half-button").forEach(b => b.addEventListener("click", () => { select(b.dataset.half); render(); }));

  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || help.isOpen()) return;
    const key = event.key.toLowerCase();
    if (key === "enter") { event.preventDefault(); client.submit(); }
    else if (key === "u") { event.preventDefault(); client.undo(); }
    else if (key === "l" || key === "r") { select(key === "l" ? "left" : "right"); render(); }
    else if (key === "+" || key === "=") setZoom(zoom * 1.25);
    else if (key === "-") setZoom(zoom / 1.25);
    else if (key === "delete" || key === "backspace") { boxes[active] = null; render(); }
    else if (key === "h" || key === "?") help.open();
  });
  client.start();
})();
