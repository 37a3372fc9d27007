// The labeling page: fetch the next open question, show it, take the answer by key or button.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const LABEL_TEXT = { FIRST: "first", SECOND: "second", EQUAL: "equal", INCOMPARABLE: "can't tell" };
  const KEYS = { ArrowLeft: "FIRST", ArrowRight: "SECOND", "=": "EQUAL", x: "INCOMPARABLE", X: "INCOMPARABLE" };

  let annotator = "";
  let current = null;        // the question shown
  let windowS = 5;           // reply window, from the server
  let deadline = 0;          // ms timestamp when the countdown reaches 0 (0: not running)
  let busy = false;          // an answer or a fetch is in flight
  let pollTimer = null;

  function setStatus(text) { $("status").textContent = text; }

  function setCounts(body) {
    if (!body) return;
    if (body.queued !== undefined) $("queued").textContent = body.queued;
    if (body.answered !== undefined) $("answers-all").textContent = body.answered;
    if (body.answered_by_you !== undefined) $("answers-mine").textContent = body.answered_by_you;
    else if (body.per_annotator) $("answers-mine").textContent = body.per_annotator[annotator] || 0;
    if (body.reply_window_s) windowS = body.reply_window_s;
  }

  function enableButtons(on) {
    document.querySelectorAll(".buttons button").forEach((b) => { b.disabled = !on; });
  }

  function clearQuestion() {
    current = null;
    deadline = 0;
    $("question").dataset.queryId = "";
    enableButtons(false);
    for (const kind of ["state", "goal1", "goal2"]) {
      $("img-" + kind).removeAttribute("src");
    }
    $("goal1-id").textContent = "";
    $("goal2-id").textContent = "";
    $("countdown").textContent = "–";
    $("countdown-bar").style.width = "0%";
  }

  function schedule(ms) {
    clearTimeout(pollTimer);
    pollTimer = setTimeout(fetchNext, ms);
  }

  async function fetchNext() {
    if (!annotator || busy || current) return;
    busy = true;
    let result;
    try {
      result = await HHP.api("/api/next?annotator=" + encodeURIComponent(annotator));
    } catch (e) {
      busy = false;
      setStatus("Cannot reach the server; retrying…");
      schedule(2000);
      return;
    }
    busy = false;
    if (result.status === 401) { setStatus("Wrong or missing token: open the address given by the server."); return; }
    if (!result.ok) { setStatus("Server error " + result.status + "; retrying…"); schedule(2000); return; }
    setCounts(result.body);
    if (!result.body.query) {
      setStatus("No question waiting; the next one appears here by itself.");
      schedule(1000);
      return;
    }
    await show(result.body.query);
  }

  async function show(query) {
    current = query;
    $("question").dataset.queryId = query.query_id;
    $("goal1-id").textContent = "#" + query.goal1;
    $("goal2-id").textContent = "#" + query.goal2;
    const loads = [];
    for (const kind of ["state", "goal1", "goal2"]) {
      const img = $("img-" + kind);
      const url = query.images[kind];
      if (url) {
        img.src = HHP.withToken(url);
        loads.push(img.decode().catch(() => null));
      } else {
        img.removeAttribute("src");
        img.alt = "(no image)";
      }
    }
    await Promise.all(loads);        // the countdown starts once the images are visible
    if (current !== query) return;
    enableButtons(true);
    setStatus("In the current state, which sub-goal is better?");
    deadline = performance.now() + windowS * 1000;
    tick();
  }

  function tick() {
    if (!current || !deadline) return;
    const left = Math.max(0, deadline - performance.now());
    $("countdown").textContent = (left / 1000).toFixed(1) + " s";
    $("countdown-bar").style.width = (100 * left / (windowS * 1000)).toFixed(1) + "%";
    if (left <= 0) { submit("INCOMPARABLE", true); return; }
    requestAnimationFrame(tick);
  }

  async function submit(label, timedOut = false) {
    if (!current || busy) return;
    const query = current;
    busy = true;
    deadline = 0;
    enableButtons(false);
    let result;
    try {
      result = await HHP.api("/api/answer", {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ query_id: query.query_id, label, annotator }),
      });
    } catch (e) {
      busy = false;
      setStatus("Cannot reach the server; answer again.");
      enableButtons(true);
      return;
    }
    busy = false;
    const item = document.createElement("li");
    if (result.ok) {
      setCounts(result.body);
      item.textContent = `#${query.goal1} vs #${query.goal2}: ${LABEL_TEXT[label]}` + (timedOut ? " (time ran out)" : "");
    } else if (result.status === 409 || result.status === 404) {
      item.textContent = `#${query.goal1} vs #${query.goal2}: answered by someone else`;
    } else {
      setStatus("The server refused the answer (" + result.status + "): " + JSON.stringify(result.body));
      enableButtons(true);
      return;
    }
    $("history").prepend(item);
    clearQuestion();
    fetchNext();
  }

  function start() {
    const name = $("annotator").value.trim();
    if (!name) { setStatus("Type your name above and press Enter to start."); return; }
    if (name === annotator) return;
    annotator = name;
    try { localStorage.setItem("sb3_hhp.annotator", name); } catch (e) { /* private mode */ }
    $("answers-mine").textContent = "0";
    clearQuestion();
    fetchNext();
  }

  document.addEventListener("keydown", (event) => {
    if (event.target === $("annotator")) {
      if (event.key === "Enter") { $("annotator").blur(); start(); }
      return;
    }
    const label = KEYS[event.key];
    if (label && current) { event.preventDefault(); submit(label); }
  });
  $("annotator").addEventListener("change", start);
  document.querySelectorAll(".buttons button").forEach((button) => {
    button.addEventListener("click", () => submit(button.dataset.label));
  });
  $("gallery-link").href = HHP.withToken("/gallery");

  // Keep the queue length fresh while a question is shown.
  setInterval(async () => {
    if (!annotator) return;
    try {
      const result = await HHP.api("/api/stats");
      if (result.ok) setCounts(result.body);
    } catch (e) { /* the next call reports it */ }
  }, 3000);

  let saved = HHP.params.get("annotator") || "";
  try { saved = saved || localStorage.getItem("sb3_hhp.annotator") || ""; } catch (e) { /* private mode */ }
  $("annotator").value = saved;
  if (saved) start();
})();
