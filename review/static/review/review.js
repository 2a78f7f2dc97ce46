// Curator review pages: decision keys on a card, select-all on the queue, "use this answer"
// on a dispute. Decisions go as JSON with the CSRF token in the X-CSRFToken header and the
// review version the page was rendered with; a 409 shows who changed the card meanwhile.
(function () {
  "use strict";

  const GRADE_KEYS = { "1": "few", "2": "some", "3": "failure" };

  function typing(event) {
    const target = event.target;
    return target && (target.isContentEditable || ["INPUT", "TEXTAREA", "SELECT"].includes(target.tagName));
  }

  function cardPage(root) {
    const cfg = root.dataset;
    const alertBox = document.getElementById("review-alert");
    const help = document.getElementById("review-help");
    const wiggle = document.getElementById("wiggle");
    let busy = false;  // one decision at a time: a held key sends once

    const show = (text, kind) => {
      alertBox.textContent = text;
      alertBox.className = "review-alert review-alert-" + kind;
      alertBox.hidden = false;
    };
    const addLink = (href, text) => {
      const link = document.createElement("a");
      link.href = href;
      link.textContent = text;
      alertBox.append(" ", link);
    };

    // A card held back (a dispute, an undecided orientation, a stale result) keeps Accept and
    // the grade buttons disabled; their keys say why, with the dispute's link, instead of posting.
    function sayWhyHeldBack() {
      const why = document.getElementById("card-blockers-why");
      show(why ? why.textContent : "This card cannot be accepted now.", "conflict");
      for (const dispute of document.querySelectorAll("#card-blockers a.dispute-link")) addLink(dispute.href, dispute.textContent);
    }

    async function decide(action, grade) {
      if (busy || !cfg.version) return;
      if (cfg.heldBack && (action === "accept" || action === "change")) { sayWhyHeldBack(); return; }
      busy = true;
      show("Saving…", "info");
      const body = {
        action, grade: grade || null, version: Number(cfg.version), results: cfg.results || null,
        note: (document.getElementById("note") || {}).value || "",
        kind: (document.getElementById("send-back-kind") || {}).value || "crop",
      };
      try {
        const response = await fetch(cfg.decideUrl, {
          method: "POST", credentials: "same-origin", body: JSON.stringify(body),
          headers: { "Content-Type": "application/json", "Accept": "application/json", "X-CSRFToken": cfg.csrf },
        });
        let data = {};
        try { data = await response.json(); } catch (e) { /* an HTML error page */ }
        if (!response.ok) {
          const message = (data.error && data.error.message) || ("The server answered " + response.status);
          show(message, response.status === 409 ? "conflict" : "error");
          const login = data.error && data.error.login_url;
          if (login || response.status === 401) {  // the session expired: say so, with the way back
            addLink(login || "/auth/login?next=" + encodeURIComponent(window.location.pathname), "Log in again");
          }
          // Held back by a dispute since the page was drawn: the way to settle it, and back here.
          if (data.error && data.error.dispute_url) addLink(data.error.dispute_url, "Resolve the dispute");
          busy = false;
          return;
        }
        window.location.assign(data.next_url);
      } catch (err) {
        show("Could not reach the server: " + err.message, "error");
        busy = false;
      }
    }

    const go = (url) => { if (url) window.location.assign(url); };

    document.addEventListener("keydown", (event) => {
      if (event.ctrlKey || event.metaKey || event.altKey || typing(event)) return;
      const key = event.key;
      if (key === "?") { help.hidden = !help.hidden; event.preventDefault(); return; }
      if (key === "Escape") { help.hidden = true; return; }
      if (!help.hidden) return;
      if (key === "a") decide("accept");
      else if (GRADE_KEYS[key]) decide("change", GRADE_KEYS[key]);
      else if (key === "b") decide("send_back");
      else if (key === "r") decide("reject");
      else if (key === "d") { const dispute = document.querySelector("#card-blockers a.dispute-link"); if (dispute) go(dispute.href); else return; }
      else if (key === "o") { const first = document.querySelector("#orientation-form select"); if (first) { first.focus(); first.scrollIntoView({ block: "center" }); } else return; }
      else if (key === "j") go(cfg.nextUrl);
      else if (key === "k") go(cfg.prevUrl);
      else if (key === "w" && wiggle) wiggle.classList.toggle("paused");
      else return;
      event.preventDefault();
    });

    // With script on, the buttons take the same path as the keys (no full-page form post).
    const form = document.getElementById("decision-form");
    if (form) {
      form.addEventListener("submit", (event) => {
        const choice = event.submitter && event.submitter.value;
        if (!choice) return;
        event.preventDefault();
        const [action, grade] = choice.split(":");
        decide(action, grade);
      });
    }
    if (wiggle) wiggle.addEventListener("click", () => wiggle.classList.toggle("paused"));
    // The list of keys is one click away too (the line under the buttons says so).
    const showKeys = document.getElementById("show-keys");
    if (showKeys) {
      showKeys.hidden = false;
      showKeys.addEventListener("click", () => { help.hidden = false; });
    }
    help.addEventListener("click", (event) => { if (event.target === help || event.target.closest("#close-keys")) help.hidden = true; });
    root.classList.add("has-keys");
    root.dataset.ready = "true";  // keys work from here on (tests wait for it)
  }

  function queuePage() {
    const all = document.getElementById("select-all");
    if (!all) return;
    const boxes = () => document.querySelectorAll('#bulk-form input[name="item"]');
    all.addEventListener("change", () => { for (const box of boxes()) box.checked = all.checked; });
  }

  function disputePage() {
    for (const button of document.querySelectorAll(".use-answer")) {
      button.addEventListener("click", () => {
        const answer = JSON.parse(button.dataset.answer);
        for (const half of ["left", "right"]) {
          ["x0", "y0", "x1", "y1"].forEach((corner, i) => {
            const input = document.querySelector(`input[name="${half}_${corner}"]`);
            if (input && answer[half]) {
              input.value = answer[half][i];
              input.dispatchEvent(new Event("input", { bubbles: true }));  // the box editor redraws
            }
          });
        }
      });
    }
  }

  const root = document.getElementById("review-card");
  if (root) cardPage(root);
  queuePage();
  disputePage();
})();
