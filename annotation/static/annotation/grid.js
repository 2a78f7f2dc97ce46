// The confirm grid: 24-48 cards shown as the pipeline will use them; a card that looks right
// takes no click at all. Tap (or U / N / D on the focused card) only what looks wrong; one
// Submit (or Enter) sends the whole grid under one idempotency key, reused on retry, so a
// double click or a lost reply never stores a card twice. Arrows move the focus between cards
// (up and down by the number of columns the layout has now). No inline script (CSP
// script-src 'self'); settings come from data-* attributes, the questions (each tap's answer
// key and hotkey, annotation/questions.py) from the page's JSON block; the API is authenticated by the
// signed worker token, as the judge and crop pages (no cookies: MTurk frames this page).
(function () {
  "use strict";
  const root = document.getElementById("crowd-task");
  if (!root) return;
  const cfg = root.dataset;
  const controls = document.getElementById("task-controls");
  const grid = document.getElementById("grid");
  const template = document.getElementById("grid-card");
  const status = document.getElementById("status");
  const errorBox = document.getElementById("error");
  const answered = document.getElementById("answered");
  const position = document.getElementById("position");
  const marked = document.getElementById("marked");
  const submitButton = document.getElementById("submit-answer");
  const help = document.getElementById("help");
  const questions = JSON.parse(document.getElementById("questions").textContent);
  const KEYS = Object.fromEntries(questions.map(q => [q.hotkey, q.key]));
  const untapped = () => Object.fromEntries(questions.map(q => [q.key, false]));
  const FINISHED = {
    batch_complete: ["All done, thank you!", "You have checked every card open to you. New cards may open later: keep this link, it brings you back to your place."],
    nothing_left_for_worker: ["All done, thank you!", "You have checked every card open to you. New cards may open later: keep this link, it brings you back to your place."],
    all_reserved: ["Nothing for you right now", "Other people hold the remaining cards."],
    worker_flagged: ["Thank you", "Thank you for your work; there are no more tasks for you."],
  };
  let cards = [];   // [{token, element, taps: {flag: bool}}]
  let focused = 0;
  let gridKey = null;
  let busy = false;

  const fail = (text) => { errorBox.textContent = text; errorBox.hidden = false; };
  const clearError = () => { errorBox.hidden = true; errorBox.textContent = ""; };
  const newKey = () => window.KeystoneTasks.newKey().slice(0, 40);
  const api = window.KeystoneTasks.client(cfg.workerToken);

  function countMarked() {
    const wrong = cards.filter(c => Object.values(c.taps).some(Boolean)).length;
    marked.textContent = wrong ? wrong + " of " + cards.length + " marked wrong" : "None marked: all look right";
  }

  function toggle(index, flag) {
    const card = cards[index];
    if (!card || busy) return;
    card.taps[flag] = !card.taps[flag];
    const button = card.element.querySelector('[data-flag="' + flag + '"]');
    button.setAttribute("aria-pressed", String(card.taps[flag]));
    card.element.classList.toggle("is-wrong", Object.values(card.taps).some(Boolean));
    countMarked();
  }

  function focusCard(index, scroll) {
    if (!cards.length) return;
    focused = Math.max(0, Math.min(cards.length - 1, index));
    cards.forEach((c, i) => { c.element.tabIndex = i === focused ? 0 : -1; });
    cards[focused].element.focus({ preventScroll: !scroll });
  }

  function columns() {
    // Cards sharing the first card's top edge make one row of the layout as it is now.
    if (cards.length < 2) return 1;
    const top = cards[0].element.offsetTop;
    const n = cards.findIndex(c => c.element.offsetTop !== top);
    return n < 0 ? cards.length : n;
  }

  function show(list) {
    grid.replaceChildren();
    cards = list.map((task, i) => {
      const element = template.content.firstElementChild.cloneNode(true);
      const image = element.querySelector("img");
      image.src = task.picture_url;
      image.alt = "Card " + (i + 1) + " of " + list.length + ": its left photo and, under it, its depth in colours";
      element.setAttribute("aria-label", "Card " + (i + 1));
      const card = { token: task.token, element, taps: untapped() };
      element.querySelectorAll(".tap").forEach(button => {
        button.addEventListener("click", () => { toggle(i, button.dataset.flag); focusCard(i, false); });
      });
      element.addEventListener("focus", () => { focused = i; });
      grid.appendChild(element);
      return card;
    });
    gridKey = newKey();
    position.textContent = "Grid of " + cards.length + " cards";
    status.textContent = "Leave the cards that look right. Mark what looks wrong, then Submit.";
    submitButton.disabled = false;
    countMarked();
    focusCard(0, false);
  }

  function finished(reason, retryAfter) {
    grid.replaceChildren();
    cards = [];
    submitButton.disabled = true;
    if (cfg.nextKindUrl && reason !== "worker_flagged") { window.location.assign(cfg.nextKindUrl); return; }
    if (cfg.provider === "prolific" && cfg.finishUrl && reason !== "all_reserved") { window.location.assign(cfg.finishUrl); return; }
    const words = FINISHED[reason] || ["No more cards right now", "Come back later with this same link."];
    let message = words[1];
    if (reason === "all_reserved" && retryAfter) {
      message += " Come back after " + new Date(retryAfter).toLocaleTimeString([], { hour: "2-digit", minute: "2-digit" }) +
        ": cards they do not finish come back to you.";
    }
    document.getElementById("finished-title").textContent = words[0];
    document.getElementById("finished-message").textContent = message;
    document.getElementById("finished").hidden = false;
    controls.hidden = true;
    root.classList.add("is-finished");
    position.textContent = "";
  }

  async function load() {
    const data = await api(controls.dataset.gridUrl, {});
    answered.textContent = data.answered;
    if (data.cards.length) show(data.cards); else finished(data.reason, data.retry_after);
  }

  async function submit() {
    if (cfg.preview === "true" || busy || !cards.length) return;
    busy = true; submitButton.disabled = true; clearError();
    status.textContent = "Sending…";
    const answers = cards.map(c => ({ token: c.token, taps: c.taps }));
    const send = () => api(controls.dataset.gridSubmitUrl, { key: gridKey, answers });
    const lapsed = (refusal) => refusal.status === 409 && /expired/.test(refusal.message);
    try {
      let data;
      try {
        data = await send();
      } catch (err) {
        // The grid's holds lapsed while the worker looked: renew them and send the same
        // answers again under the same key (anything already stored is a duplicate).
        if (!lapsed(err)) throw err;
        await renewAll(cards.map(c => c.token));
        data = await send();
      }
      const late = data.refused.filter(lapsed);
      if (late.length) {
        await renewAll(late.map(r => r.token));
        data = await send();
      }
      answered.textContent = data.answered;
      if (data.finish && data.finish.post) { window.KeystoneTasks.postToMTurk(data.finish.post); return; }
      if (data.refused.length) fail(data.refused.length + " card(s) could not be saved: " + data.refused[0].message);
      busy = false;
      await load();
    } catch (err) {
      fail(err.message);
      status.textContent = "Not sent.";
      // A grid that lapsed or was taken back cannot be sent again: fetch a fresh one.
      if (err.status === 409 || err.status === 403 || err.status === 404) { busy = false; await load().catch(e => fail(e.message)); }
      else submitButton.disabled = false;
    } finally { busy = false; }
  }

  async function renewAll(tokens) {
    for (const token of tokens) await api(cfg.renewUrl, { token });
  }


  // The instructions: shown the first time (remembered) and on demand (button or H).
  const seen = () => { try { return localStorage.getItem("keystone-grid-help-seen") === "1"; } catch (e) { return false; } };
  // As the judge page's help (tasks.js): opened at its top with its example pictures loading;
  // focusing the Start button at the end used to scroll a phone's dialog down to it.
  const openHelp = () => {
    if (!help || typeof help.showModal !== "function" || help.open) return;
    help.querySelectorAll("img[loading=lazy]").forEach(img => { img.loading = "eager"; });
    help.showModal();
    const start = help.querySelector("form[method=dialog] button");
    if (start) start.focus({ preventScroll: true });
    help.scrollTop = 0;
  };
  if (help) {
    help.addEventListener("close", () => { try { localStorage.setItem("keystone-grid-help-seen", "1"); } catch (e) { /* iframes may block storage */ } focusCard(focused, false); });
    help.addEventListener("click", (event) => { if (event.target === help) help.close(); });
  }
  document.getElementById("show-help").addEventListener("click", openHelp);
  submitButton.addEventListener("click", submit);

  document.addEventListener("keydown", (event) => {
    if (event.ctrlKey || event.metaKey || event.altKey || (help && help.open)) return;
    const key = event.key.toLowerCase();
    const moves = { arrowleft: -1, arrowright: 1, arrowup: -columns(), arrowdown: columns() };
    if (key in moves && cards.length) { event.preventDefault(); focusCard(focused + moves[key], true); }
    else if (KEYS[key]) { event.preventDefault(); toggle(focused, KEYS[key]); }
    else if (key === "enter") {
      // Enter on a focused toggle button would also click it: the grid's Enter is Submit.
      event.preventDefault(); submit();
    }
    else if (key === "h" || key === "?") { event.preventDefault(); openHelp(); }
  });

  if (cfg.preview === "true" || root.classList.contains("is-finished")) return;
  if (!seen()) openHelp();
  load().catch(err => fail(err.message));
})();
