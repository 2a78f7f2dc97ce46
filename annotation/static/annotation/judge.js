// The judge page: one key or one tap per judgement, Enter or the Submit button sends, U undoes,
// H (or the Help button) helps. No inline script (CSP script-src 'self'); settings come from
// data-* attributes, the questions from the page's JSON block (annotation/questions.py: each
// one's answer key, hotkey, the answer of an untouched box, its widget).
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const form = document.getElementById("judge-form");
  const image = document.getElementById("card-image");
  const questions = JSON.parse(document.getElementById("questions").textContent);
  const boxOf = (question) => form.querySelector('input[name="' + question.key + '"]');
  const byHotkey = new Map(questions.map(q => [q.hotkey, q]));
  // The eye-order pictures (the task's wiggle_urls): tapping one picks it, the same answer as
  // its question's box (S).
  const eyeQuestion = questions.find(q => q.widget === "eye_order");
  const eyeBox = eyeQuestion ? boxOf(eyeQuestion) : null;
  const eyeOrders = { "as-is": document.getElementById("eye-order-as-is"), swapped: document.getElementById("eye-order-swapped") };
  const picks = form.querySelectorAll(".eye-order-pick");
  const showPick = () => {
    if (!eyeBox) return;
    picks.forEach(pick => { pick.setAttribute("aria-pressed", String((pick.dataset.swapped === "true") === eyeBox.checked)); });
  };

  const client = window.KeystoneTasks.create(root, {
    kind: "judge",
    undoneText: "Undone: judge this card again.",
    cardText: (n, total) => "Card " + n + (total ? " of " + total : ""),
    show(task) {
      image.src = task.image_url; image.hidden = false; form.reset(); showPick();
      for (const order in eyeOrders) {
        if (!eyeOrders[order]) continue;
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
    restore(answer) {
      // An undone answer: tick the boxes it ticked (an answer other than an untouched box's).
      questions.forEach(q => { if (q.key in answer) boxOf(q).checked = answer[q.key] !== q.default; });
      showPick();
    },
    hide() { image.hidden = true; for (const order in eyeOrders) if (eyeOrders[order]) eyeOrders[order].hidden = true; },
    answer() {
      // A ticked box gives the other answer than an untouched one ("Not a stereo pair": is_stereo false).
      const answer = {};
      questions.forEach(q => { answer[q.key] = boxOf(q).checked ? !q.default : q.default; });
      return answer;
    },
  });
  const help = window.KeystoneTasks.instructions(document.getElementById("help"), "keystone-crowd-help-seen");

  form.addEventListener("submit", (event) => { event.preventDefault(); client.submit(); });
  if (eyeBox) eyeBox.addEventListener("change", showPick);
  picks.forEach(pick => pick.addEventListener("click", () => {
    eyeBox.checked = pick.dataset.swapped === "true";
    showPick();
  }));
  document.getElementById("undo").addEventListener("click", client.undo);
  document.getElementById("show-help").addEventListener("click", help.open);
  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || help.isOpen()) return;
    const key = event.key.toLowerCase();
    const question = byHotkey.get(key);
    const box = question ? boxOf(question) : null;
    if (box) { event.preventDefault(); if (!box.disabled) box.checked = !box.checked; showPick(); return; }
    if (key === "enter") { event.preventDefault(); client.submit(); }
    else if (key === "u") { event.preventDefault(); client.undo(); }
    else if (key === "h" || key === "?") { event.preventDefault(); help.open(); }
  });
  client.start();
})();
