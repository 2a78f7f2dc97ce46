// A small box editor for crop disputes: the left and right crop boxes drawn over the card, in
// the card's original pixels (the SVG's viewBox is the card size), kept in the form's number
// inputs (left_x0 ... right_y1) so the form posts exactly what is drawn. Pointer events: mouse,
// pen and touch alike; drag empty space to draw the chosen half's box, drag a box to move it,
// drag a corner handle (large enough for a finger) to resize.
(function () {
  "use strict";
  const editor = document.getElementById("box-editor");
  if (!editor) return;
  const svg = editor.querySelector("svg");
  const W = Number(editor.dataset.width), H = Number(editor.dataset.height);
  const NS = "http://www.w3.org/2000/svg";
  const CORNERS = ["x0", "y0", "x1", "y1"];
  let active = "left";
  let drag = null;

  const input = (half, corner) => document.querySelector(`input[name="${half}_${corner}"]`);
  const read = (half) => {
    const values = CORNERS.map((c) => parseFloat(input(half, c).value));
    return values.every(Number.isFinite) ? values : null;
  };
  const write = (half, box) => {
    CORNERS.forEach((c, i) => { input(half, c).value = box ? String(Math.round(box[i])) : ""; });
  };
  const clamp = (v, lo, hi) => Math.min(hi, Math.max(lo, v));

  function point(event) {
    const r = svg.getBoundingClientRect();
    return [clamp((event.clientX - r.left) / r.width * W, 0, W), clamp((event.clientY - r.top) / r.height * H, 0, H)];
  }

  const shapes = {};
  for (const half of ["left", "right"]) {
    const rect = document.createElementNS(NS, "rect");
    rect.setAttribute("class", `box box-${half} edit`);
    rect.dataset.half = half;
    svg.appendChild(rect);
    const handles = [];
    for (const corner of ["nw", "ne", "sw", "se"]) {
      const h = document.createElementNS(NS, "rect");
      h.setAttribute("class", `box-${half} handle`);
      h.dataset.half = half;
      h.dataset.corner = corner;
      svg.appendChild(h);
      handles.push(h);
    }
    shapes[half] = { rect, handles };
  }

  function draw() {
    const scale = W / Math.max(1, svg.getBoundingClientRect().width);  // card px per screen px
    const size = 22 * scale;  // a 44 px touch target, centred on the corner
    for (const half of ["left", "right"]) {
      const box = read(half), { rect, handles } = shapes[half];
      const shown = !!box;
      rect.style.display = shown ? "" : "none";
      for (const h of handles) h.style.display = shown ? "" : "none";
      if (!shown) continue;
      const [x0, y0, x1, y1] = box;
      rect.setAttribute("x", Math.min(x0, x1)); rect.setAttribute("y", Math.min(y0, y1));
      rect.setAttribute("width", Math.abs(x1 - x0)); rect.setAttribute("height", Math.abs(y1 - y0));
      for (const h of handles) {
        const cx = h.dataset.corner.includes("w") ? x0 : x1, cy = h.dataset.corner.includes("n") ? y0 : y1;
        h.setAttribute("x", cx - size / 2); h.setAttribute("y", cy - size / 2);
        h.setAttribute("width", size); h.setAttribute("height", size);
      }
    }
  }

  svg.addEventListener("pointerdown", (event) => {
    event.preventDefault();
    const target = event.target, p = point(event);
    if (target.dataset && target.dataset.corner) {
      drag = { mode: "corner", half: target.dataset.half, corner: target.dataset.corner };
    } else if (target.dataset && target.dataset.half && target.classList.contains("edit")) {
      drag = { mode: "move", half: target.dataset.half, start: p, box: read(target.dataset.half) };
    } else {
      drag = { mode: "draw", half: active, start: p };
      write(active, [p[0], p[1], p[0], p[1]]);
    }
    svg.setPointerCapture(event.pointerId);
    draw();
  });
  svg.addEventListener("pointermove", (event) => {
    if (!drag) return;
    const p = point(event);
    if (drag.mode === "draw") {
      write(drag.half, [drag.start[0], drag.start[1], p[0], p[1]]);
    } else if (drag.mode === "move") {
      const [x0, y0, x1, y1] = drag.box;
      const dx = clamp(p[0] - drag.start[0], -Math.min(x0, x1), W - Math.max(x0, x1));
      const dy = clamp(p[1] - drag.start[1], -Math.min(y0, y1), H - Math.max(y0, y1));
      write(drag.half, [x0 + dx, y0 + dy, x1 + dx, y1 + dy]);
    } else {
      const box = read(drag.half);
      if (drag.corner.includes("w")) box[0] = p[0]; else box[2] = p[0];
      if (drag.corner.includes("n")) box[1] = p[1]; else box[3] = p[1];
      write(drag.half, box);
    }
    draw();
  });
  const finish = () => {
    if (!drag) return;
    const box = read(drag.half);
    if (box) {  // store corners ordered: x0 < x1, y0 < y1
      write(drag.half, [Math.min(box[0], box[2]), Math.min(box[1], box[3]), Math.max(box[0], box[2]), Math.max(box[1], box[3])]);
    }
    drag = null;
    draw();
  };
  svg.addEventListener("pointerup", finish);
  svg.addEventListener("pointercancel", finish);

  for (const button of document.querySelectorAll(".box-editor-tools [data-half]")) {
    button.addEventListener("click", () => {
      active = button.dataset.half;
      for (const other of document.querySelectorAll(".box-editor-tools [data-half]")) {
        other.setAttribute("aria-pressed", String(other === button));
      }
    });
  }
  const clear = document.getElementById("clear-box");
  if (clear) clear.addEventListener("click", () => { write(active, null); draw(); });
  document.getElementById("resolve-form").addEventListener("input", draw);
  window.addEventListener("resize", draw);
  draw();
  editor.dataset.ready = "true";
})();
