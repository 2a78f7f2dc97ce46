// The judge page: keyboard first (one key per judgement, Enter submits, U undoes, H helps).
// No inline script (CSP script-src 'self'); settings come from data-* attributes.
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const form = document.getElementById("judge-form");
  const image = document.getElementById("card-image");

  const client = window.KeystoneTasks.create(root, {
    kind: "judge",
    undoneText: "Undone: judge this card again.",
    cardText: (n) => "Card " + n,
    show(task) { image.src = task.image_url; image.hidden = false; form.reset(); },
    hide() { image.hidden = true; },
    answer() {
      return {
        is_stereo: !form.elements.not_stereo.checked,
        upside_down: form.elements.upside_down.checked,
        inverted: form.elements.inverted.checked,
      };
    },
  });
  const help = window.KeystoneTasks.instructions(document.getElementById("help"), "keystone-crowd-help-seen");

  form.addEventListener("submit", (event) => { event.preventDefault(); client.submit(); });
  document.getElementById("undo").addEventListener("click", client.undo);
  document.getElementById("show-help").addEventListener("click", help.open);
  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || help.isOpen()) return;
    const key = event.key.toLowerCase();
    const box = form.querySelector('input[data-key="' + key + '"]');
    if (box) { event.preventDefault(); box.checked = !box.checked; return; }
    if (key === "enter") { event.preventDefault(); client.submit(); }
    else if (key === "u") { event.preventDefault(); client.undo(); }
    else if (key === "h" || key === "?") { event.preventDefault(); help.open(); }
  });
  client.start();
})();
