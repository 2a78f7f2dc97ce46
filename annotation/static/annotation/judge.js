// The judge page: keyboard first, the next card preloaded, idempotent submits.
// No inline script (CSP script-src 'self'); settings come from data-* attributes.
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const cfg = root.dataset;
  const preview = cfg.preview === "true";
  const form = document.getElementById("judge-form");
  const image = document.getElementById("card-image");
  const status = document.getElementById("status");
  const errorBox = document.getElementById("error");
  const submitButton = document.getElementById("submit-answer");
  const help = document.getElementById("help");
  const answered = document.getElementById("answered");
  const HELP_SEEN = "keystone-crowd-help-seen";

  let queue = [];          // open tasks, current first; the second one's image is preloaded
  let shown = null;        // reservation token on screen: refetching must not reset its answers
  let busy = false;        // one request at a time: a double Enter or double click sends once
  const keys = new Map();  // reservation token -> idempotency key, reused on retry

  function showHelp() { if (help && typeof help.showModal === "function" && !help.open) help.showModal(); }
  function seenHelp() { try { return localStorage.getItem(HELP_SEEN) === "1"; } catch (e) { return false; } }
  function markHelpSeen() { try { localStorage.setItem(HELP_SEEN, "1"); } catch (e) { /* iframes may block storage */ } }

  function say(text) { status.textContent = text; }
  function fail(text) { errorBox.textContent = text; errorBox.hidden = false; }
  function clearError() { errorBox.hidden = true; errorBox.textContent = ""; }

  function newKey() {
    if (window.crypto && crypto.randomUUID) return crypto.randomUUID();
    return Date.now().toString(36) + Math.random().toString(36).slice(2);
  }

  async function api(url, body) {
    const response = await fetch(url, {
      method: "POST",
      headers: { "Content-Type": "application/json", "X-Crowd-Token": cfg.workerToken },
      body: JSON.stringify(body || {}),
      credentials: "omit",
    });
    let data = {};
    try { data = await response.json(); } catch (e) { /* an HTML error page */ }
    if (!response.ok) {
      const message = (data.error && data.error.message) || ("The server answered " + response.status);
      const err = new Error(message);
      err.status = response.status;
      throw err;
    }
    return data;
  }

  function resetForm() { form.reset(); }

  function show() {
    const task = queue[0];
    if (!task) { image.hidden = true; shown = null; return; }
    if (shown === task.token) return;
    shown = task.token;
    image.src = task.image_url;
    image.hidden = false;
    say("Card " + (Number(answered.textContent) + 1));
    if (queue[1]) { const next = new Image(); next.src = queue[1].image_url; }  // preload
    resetForm();
    submitButton.disabled = false;
  }

  function finished(reason) {
    image.hidden = true;
    submitButton.disabled = true;
    const messages = {
      batch_complete: "All cards are done. Thank you!",
      nothing_left_for_worker: "You have judged every card available to you. Thank you!",
      all_reserved: "Other people hold the remaining cards; try again in a few minutes.",
      worker_flagged: "Thank you for your work; there are no more tasks for you.",
    };
    say(messages[reason] || "No more cards right now.");
    if (cfg.provider === "prolific" && cfg.finishUrl && reason !== "all_reserved") {
      window.location.assign(cfg.finishUrl);
    }
  }

  async function fetchTasks() {
    const data = await api(cfg.nextUrl, { kind: "judge" });
    answered.textContent = data.answered;
    const known = new Set(queue.map(t => t.token));
    for (const task of data.tasks) if (!known.has(task.token)) queue.push(task);
    if (queue.length) show(); else finished(data.reason);
  }

  function answerFromForm() {
    return {
      is_stereo: !form.elements.not_stereo.checked,
      upside_down: form.elements.upside_down.checked,
      inverted: form.elements.inverted.checked,
    };
  }

  function postToMTurk(post) {
    const out = document.createElement("form");
    out.method = "POST";
    out.action = post.url;
    for (const [name, value] of Object.entries(post.fields)) {
      const input = document.createElement("input");
      input.type = "hidden"; input.name = name; input.value = value;
      out.appendChild(input);
    }
    document.body.appendChild(out);
    out.submit();
  }

  async function submitAnswer() {
    if (preview || busy || !queue[0]) return;
    busy = true; submitButton.disabled = true; clearError();
    const task = queue[0];
    if (!keys.has(task.token)) keys.set(task.token, newKey());
    try {
      const data = await api(cfg.submitUrl, { token: task.token, key: keys.get(task.token), answer: answerFromForm() });
      answered.textContent = data.answered;
      queue.shift();
      if (data.finish && data.finish.post) { postToMTurk(data.finish.post); return; }
      if (queue.length) {
        // The preloaded next card is on screen: let the annotator go on at once and top the
        // queue up in the background (keys pressed meanwhile must not be dropped).
        show();
        busy = false;
        fetchTasks().catch(err => fail(err.message));
        return;
      }
      await fetchTasks();
    } catch (err) {
      fail(err.message);
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
      shown = null;
      show();
      say("Undone: judge this card again.");
    } catch (err) { fail(err.message); } finally { busy = false; }
  }

  form.addEventListener("submit", (event) => { event.preventDefault(); submitAnswer(); });
  document.getElementById("undo").addEventListener("click", undo);
  document.getElementById("show-help").addEventListener("click", showHelp);
  if (help) help.addEventListener("close", markHelpSeen);

  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || (help && help.open)) return;
    const key = event.key.toLowerCase();
    const box = form.querySelector('input[data-key="' + key + '"]');
    if (box) { event.preventDefault(); box.checked = !box.checked; return; }
    if (key === "enter") { event.preventDefault(); submitAnswer(); }
    else if (key === "u") { event.preventDefault(); undo(); }
    else if (key === "h" || key === "?") { event.preventDefault(); showHelp(); }
  });

  if (!seenHelp()) showHelp();
  if (!preview) fetchTasks().catch(err => fail(err.message));
})();
