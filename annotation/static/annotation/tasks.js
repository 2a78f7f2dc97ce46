// The task client shared by the judge and crop pages: a queue of reserved tasks (the current
// one first, the next one's image preloaded), one request at a time, an idempotency key per
// task reused on retry, the JSON API authenticated by the signed worker token (no cookies:
// MTurk frames this page), MTurk's post-back and Prolific's completion redirect.
// Each page supplies what differs: how to show a task, read its answer, and its words.
window.KeystoneTasks = (function () {
  "use strict";

  const FINISHED = {
    batch_complete: "All cards are done. Thank you!",
    nothing_left_for_worker: "You have done every card available to you. Thank you!",
    all_reserved: "Other people hold the remaining cards; try again in a few minutes.",
    worker_flagged: "Thank you for your work; there are no more tasks for you.",
  };

  function newKey() {
    if (window.crypto && crypto.randomUUID) return crypto.randomUUID();
    return Date.now().toString(36) + Math.random().toString(36).slice(2);
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

  // page: { kind, show(task, next), hide(), answer() -> payload (throws Error to refuse),
  //         undoneText }; elements: status, error, answered, submit button.
  function create(root, page) {
    const cfg = root.dataset;
    const preview = cfg.preview === "true";
    const status = document.getElementById("status");
    const errorBox = document.getElementById("error");
    const answered = document.getElementById("answered");
    const submitButton = document.getElementById("submit-answer");
    let queue = [];
    let shown = null;   // token on screen: a refill must not reset its answer
    let busy = false;   // one request at a time: a double Enter or double click sends once
    const keys = new Map();

    const say = (text) => { status.textContent = text; };
    const fail = (text) => { errorBox.textContent = text; errorBox.hidden = false; };
    const clearError = () => { errorBox.hidden = true; errorBox.textContent = ""; };

    async function api(url, body) {
      const response = await fetch(url, {
        method: "POST", credentials: "omit", body: JSON.stringify(body || {}),
        headers: { "Content-Type": "application/json", "X-Crowd-Token": cfg.workerToken },
      });
      let data = {};
      try { data = await response.json(); } catch (e) { /* an HTML error page */ }
      if (!response.ok) {
        const err = new Error((data.error && data.error.message) || ("The server answered " + response.status));
        err.status = response.status;
        throw err;
      }
      return data;
    }

    function show(force) {
      const task = queue[0];
      if (!task) { page.hide(); shown = null; return; }
      if (shown === task.token && !force) return;
      shown = task.token;
      page.show(task);
      if (queue[1]) { const next = new Image(); next.src = queue[1].image_url; }  // preload
      say(page.cardText(Number(answered.textContent) + 1));
      submitButton.disabled = false;
    }

    function finished(reason) {
      page.hide();
      submitButton.disabled = true;
      say(FINISHED[reason] || "No more cards right now.");
      if (cfg.provider === "prolific" && cfg.finishUrl && reason !== "all_reserved") {
        window.location.assign(cfg.finishUrl);
      }
    }

    async function refill() {
      const data = await api(cfg.nextUrl, { kind: page.kind });
      answered.textContent = data.answered;
      const known = new Set(queue.map(t => t.token));
      for (const task of data.tasks) if (!known.has(task.token)) queue.push(task);
      if (queue.length) show(false); else finished(data.reason);
    }

    async function submit() {
      if (preview || busy || !queue[0]) return;
      let answer;
      try { answer = page.answer(); } catch (err) { fail(err.message); return; }
      busy = true; submitButton.disabled = true; clearError();
      const task = queue[0];
      if (!keys.has(task.token)) keys.set(task.token, newKey());
      try {
        const data = await api(cfg.submitUrl, { token: task.token, key: keys.get(task.token), answer });
        answered.textContent = data.answered;
        queue.shift();
        if (data.finish && data.finish.post) { postToMTurk(data.finish.post); return; }
        if (queue.length) {
          // The preloaded next card is on screen: let the annotator go on at once and top the
          // queue up in the background (keys pressed meanwhile must not be dropped).
          show(false);
          busy = false;
          refill().catch(err => fail(err.message));
          return;
        }
        await refill();
      } catch (err) {
        fail(err.message);  // refusals keep the answer on screen for fixing
        if (err.status === 409 || err.status === 403 || err.status === 404) {
          queue.shift();
          await refill().catch(e => fail(e.message));
        } else submitButton.disabled = false;
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
        show(true);
        say(page.undoneText);
      } catch (err) { fail(err.message); } finally { busy = false; }
    }

    function start() { if (!preview) refill().catch(err => fail(err.message)); }

    return { preview, submit, undo, start, fail, clearError, current: () => queue[0] };
  }

  // The instructions: shown the first time (remembered per page kind) and on demand.
  function instructions(help, storageKey) {
    const seen = () => { try { return localStorage.getItem(storageKey) === "1"; } catch (e) { return false; } };
    const open = () => { if (help && typeof help.showModal === "function" && !help.open) help.showModal(); };
    if (help) help.addEventListener("close", () => { try { localStorage.setItem(storageKey, "1"); } catch (e) { /* iframes may block storage */ } });
    if (!seen()) open();
    return { open, isOpen: () => Boolean(help && help.open) };
  }

  return { create, instructions };
})();
