// The task client shared by the judge and crop pages: a queue of reserved tasks (the current
// one first, the next one's image preloaded), one request at a time, an idempotency key per
// task reused on retry, the JSON API authenticated by the signed worker token (no cookies:
// MTurk frames this page), MTurk's post-back and Prolific's completion redirect.
// Each page supplies what differs: how to show a task, read its answer, and its words.
// Progress is "card n of N" per batch (the server's count of this worker's answers and of the
// items still open to them). When a kind runs out, the page moves on to the next kind with work
// (judge, then crop) or shows the finished screen without controls.
window.KeystoneTasks = (function () {
  "use strict";

  const FINISHED = {
    batch_complete: ["All done, thank you!", "You have answered every card open to you. New cards may open later: keep this link, it brings you back to your place."],
    nothing_left_for_worker: ["All done, thank you!", "You have answered every card open to you. New cards may open later: keep this link, it brings you back to your place."],
    all_reserved: ["Nothing for you right now", "Other people hold the remaining cards."],
    worker_flagged: ["Thank you", "Thank you for your work; there are no more tasks for you."],
  };
  const RENEW_BEFORE_MS = 60000;  // renew a reservation this long before it lapses while its card is on screen

  function newKey() {
    if (window.crypto && crypto.randomUUID) return crypto.randomUUID();
    return Date.now().toString(36) + Math.random().toString(36).slice(2);
  }

  // POST a JSON body with the signed worker token (no cookies: MTurk frames these pages); the
  // reply's JSON, or an Error with the server's message and the HTTP status. Shared with the grid.
  function client(workerToken) {
    return async function api(url, body) {
      const response = await fetch(url, {
        method: "POST", credentials: "omit", body: JSON.stringify(body || {}),
        headers: { "Content-Type": "application/json", "X-Crowd-Token": workerToken },
      });
      let data = {};
      try { data = await response.json(); } catch (e) { /* an HTML error page */ }
      if (!response.ok) {
        const err = new Error((data.error && data.error.message) || ("The server answered " + response.status));
        err.status = response.status;
        throw err;
      }
      return data;
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

  // page: { kind, show(task), hide(), answer() -> payload (throws Error to refuse), restore(answer)
  //         (an undone answer shown again), undoneText, cardText(n, total) }; elements: status,
  //         error, answered, position, submit button.
  function create(root, page) {
    const cfg = root.dataset;
    const preview = cfg.preview === "true";
    const status = document.getElementById("status");
    const errorBox = document.getElementById("error");
    const answered = document.getElementById("answered");
    const position = document.getElementById("position");
    const submitButton = document.getElementById("submit-answer");
    let queue = [];
    let positions = {};  // batch id -> {done, total}
    let shown = null;   // token on screen: a refill must not reset its answer
    let busy = false;   // one request at a time: a double Enter or double click sends once
    let renewTimer = null;
    const keys = new Map();

    const say = (text) => { status.textContent = text; };
    const fail = (text) => { errorBox.textContent = text; errorBox.hidden = false; };
    const clearError = () => { errorBox.hidden = true; errorBox.textContent = ""; };

    const api = client(cfg.workerToken);

    function progressText(task) {
      const p = positions[String(task.batch)];
      if (!p || !p.total) return page.cardText(Number(answered.textContent) + 1);
      return page.cardText(Math.min(p.done + 1, p.total), p.total);
    }
    function positionText(task) {
      const p = positions[String(task.batch)];
      return p && p.total ? "Card " + Math.min(p.done + 1, p.total) + " of " + p.total : "";
    }

    function scheduleRenew(task) {
      clearTimeout(renewTimer);
      const due = Date.parse(task.expires_at) - Date.now() - RENEW_BEFORE_MS;
      renewTimer = setTimeout(() => { if (shown === task.token) renew(task).catch(() => {}); }, Math.max(5000, due));
    }

    async function renew(task) {
      const data = await api(cfg.renewUrl, { token: task.token });
      task.expires_at = data.task.expires_at;
      if (shown === task.token) scheduleRenew(task);
      return task;
    }

    function show(force) {
      const task = queue[0];
      if (!task) { page.hide(); shown = null; return; }
      const text = progressText(task);
      position.textContent = positionText(task);
      if (shown === task.token && !force) return;
      shown = task.token;
      page.show(task);
      if (queue[1]) {  // preload the next card and its pictures (the eye-order ones are made on request)
        for (const url of [queue[1].image_url, ...Object.values(queue[1].wiggle_urls || {})]) { const next = new Image(); next.src = url; }
      }
      say(text);
      submitButton.disabled = false;
      scheduleRenew(task);
    }

    function finished(reason, retryAfter) {
      page.hide();
      clearTimeout(renewTimer);
      submitButton.disabled = true;
      if (cfg.nextKindUrl && reason !== "worker_flagged") { window.location.assign(cfg.nextKindUrl); return; }
      if (cfg.provider === "prolific" && cfg.finishUrl && reason !== "all_reserved") {
        window.location.assign(cfg.finishUrl);
        return;
      }
      const words = FINISHED[reason] || ["No more cards right now", "Come back later with this same link."];
      let message = words[1];
      if (reason === "all_reserved" && retryAfter) {
        const at = new Date(retryAfter);
        message += " Come back after " + at.toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" }) +
          ": cards they do not finish come back to you.";
      }
      document.getElementById("finished-title").textContent = words[0];
      document.getElementById("finished-message").textContent = message;
      document.getElementById("finished").hidden = false;
      document.getElementById("task-controls").hidden = true;
      root.classList.add("is-finished");
      position.textContent = "";
    }

    async function refill() {
      const data = await api(cfg.nextUrl, { kind: page.kind });
      answered.textContent = data.answered;
      Object.assign(positions, data.positions || {});
      const known = new Set(queue.map(t => t.token));
      for (const task of data.tasks) if (!known.has(task.token)) queue.push(task);
      if (queue.length) show(false); else finished(data.reason, data.retry_after);
    }

    async function send(task, answer) {
      if (!keys.has(task.token)) keys.set(task.token, newKey());
      return api(cfg.submitUrl, { token: task.token, key: keys.get(task.token), answer });
    }

    async function submit() {
      if (preview || busy || !queue[0]) return;
      let answer;
      try { answer = page.answer(); } catch (err) { fail(err.message); return; }
      busy = true; submitButton.disabled = true; clearError();
      const task = queue[0];
      try {
        let data;
        try {
          data = await send(task, answer);
        } catch (err) {
          // The reservation lapsed while the annotator worked: renew it and send the same
          // answer again (same key), keeping what is on screen.
          if (err.status !== 409 || !/expired/.test(err.message)) throw err;
          await renew(task);
          data = await send(task, answer);
        }
        answered.textContent = data.answered;
        const p = positions[String(task.batch)];
        if (p && !data.duplicate) p.done += 1;
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
        const p = positions[String(data.task.batch)];
        if (p && p.done > 0) p.done -= 1;
        queue = [data.task].concat(queue.filter(t => t.token !== data.task.token));
        keys.delete(data.task.token);
        show(true);
        // The withdrawn answer is back on screen to correct: Enter resends it, never a blank card.
        if (data.answer && page.restore) page.restore(data.answer);
        say(page.undoneText);
      } catch (err) { fail(err.message); } finally { busy = false; }
    }

    function start() {
      if (preview) { if (page.showPreview) page.showPreview(cfg.previewImage); return; }
      if (root.classList.contains("is-finished")) return;
      refill().catch(err => fail(err.message));
    }

    return { preview, submit, undo, start, fail, clearError, current: () => queue[0] };
  }

  // The instructions: shown the first time (remembered per page kind) and on demand (button or H).
  function instructions(help, storageKey) {
    const seen = () => { try { return localStorage.getItem(storageKey) === "1"; } catch (e) { return false; } };
    // Opened at its top with its example pictures loading: lazy pictures inside a dialog that
    // scrolls wait until they are scrolled to, and focusing the Start button at the end
    // scrolled the dialog down to it (so a phone showed the end, and blank pictures).
    const open = () => {
      if (!help || typeof help.showModal !== "function" || help.open) return;
      help.querySelectorAll("img[loading=lazy]").forEach(img => { img.loading = "eager"; });
      help.showModal();
      const start = help.querySelector("form[method=dialog] button");
      if (start) start.focus({ preventScroll: true });
      help.scrollTop = 0;
    };
    if (help) help.addEventListener("close", () => { try { localStorage.setItem(storageKey, "1"); } catch (e) { /* iframes may block storage */ } });
    // A tap outside the dialog's box closes it (phones have no Escape key).
    if (help) help.addEventListener("click", (event) => { if (event.target === help) help.close(); });
    const finishedPage = document.querySelector("#crowd-task.is-finished");
    if (!seen() && !finishedPage) open();
    return { open, isOpen: () => Boolean(help && help.open) };
  }

  return { create, instructions, client, newKey, postToMTurk };
})();
