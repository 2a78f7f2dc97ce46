// The judge page: one key or one tap per judgement, Enter or the Submit button sends, U undoes,
// H (or the Help button) helps. No inline script (CSP script-src 'self'); settings come from
// data-* attributes.
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const form = document.getElementById("judge-form");
  const image = document.getElementById("card-image");
  // The eye-order pictures (the task's wiggle_urls): tapping one picks it, the same answer as the S box.
  const eyeOrders = { "as-is": document.getElementById("eye-order-as-is"), swapped: document.getElementById("eye-order-swapped") };
  const picks = form.querySelectorAll(".eye-order-pick");
  const showPick = () => {
    picks.forEach(pick => { pick.setAttribute("aria-pressed", String((pick.dataset.swapped === "true") === form.elements.swapped.checked)); });
  };

  const client = window.KeystoneTasks.create(root, {
    kind: "judge",
    undoneText: "Undone: judge this card again.",
    cardText: (n, total) => "Card " + n + (total ? " of " + total : ""),
    show(task) {
      image.src = task.image_url; image.hidden = false; form.reset(); showPick();
      for (const order in eyeOrders) {
        const url = task.wiggle_urls && task.wiggle_urls[order];
        eyeOrders[order].hidden = !url;
        if (url) eyeOrders[order].src = url;
      }
    },
    showPreview(url) {
      // MTurk preview: a real card, read-only (nothing is reserved, nothing can be sent).
      if (!url) return;
      image.src = url; image.hidden = false;
      document.getElementById("status").textContent = "A card like the ones in this task. Accept the HIT to answer.";
      form.querySelectorAll("input, .eye-order-pick").forEach(input => { input.disabled = true; });
    },
    hide() { image.hidden = true; for (const order in eyeOrders) eyeOrders[order].hidden = true; },
    answer() {
      return {
        is_stereo: !form.elements.not_stereo.checked,
        upside_down: form.elements.upside_down.checked,
        inverted: form.elements.inverted.checked,
        swapped: form.elements.swapped.checked,
      };
    },
  });
  const help = window.KeystoneTasks.instructions(document.getElementById("help"), "keystone-crowd-help-seen");

  form.addEventListener("submit", (event) => { event.preventDefault(); client.submit(); });
  form.elements.swapped.addEventListener("change", showPick);
  picks.forEach(pick => pick.addEventListener("click", () => {
    form.elements.swapped.checked = pick.dataset.swapped === "true";
    showPick();
  }));
  document.getElementById("undo").addEventListener("click", client.undo);
  document.getElementById("show-help").addEventListener("click", help.open);
  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || help.isOpen()) return;
    const key = event.key.toLowerCase();
    const box = form.querySelector('input[data-key="' + key + '"]');
    if (box) { event.preventDefault(); if (!box.disabled) box.checked = !box.checked; showPick(); return; }
    if (key === "enter") { event.preventDefault(); client.submit(); }
    else if (key === "u") { event.preventDefault(); client.undo(); }
    else if (key === "h" || key === "?") { event.preventDefault(); help.open(); }
  });
  client.start();
})();
