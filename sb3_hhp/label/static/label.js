// The labeling page: fetch the next open question, show it, take the answer by key or button.
"use strict";

(() => {
  const $ = (id) => document.getElementById(id);
  const LABEL_TEXT = { FIRST: "left", SECOND: "right", EQUAL: "equal", INCOMPARABLE: "can't tell" };
  const KEYS = { ArrowLeft: "FIRST", ArrowRight: "SECOND", "=": "EQUAL", x: "INCOMPARABLE", X: "INCOMPARABLE" };
  const KINDS = ["state", "goal1", "goal2"];

  let annotator = "";
  let current = null;        // the question shown
  let windowS = 5;           // reply window, from the server
  let deadline = 0;          // ms timestamp when the countdown reaches 0 (0: not running)
  let shownAt = 0;           // ms timestamp when the question became answerable
  let busy = false;          // an answer or a fetch is in flight
  let showingFound = false;  // the sub-goals' images from where they were found, instead of drawn in the state
  let pollTimer = null;

  function setStatus(text) { $("status").textContent = text; }
  const show_ = (value) => (value === null || value === undefined ? "–" : String(value));

  function setCounts(body) {
    if (!body) return;
    if (body.asked !== undefined) $("asked").textContent = body.asked;
    if (body.budget !== undefined) $("budget").textContent = show_(body.budget);
    if (body.distinct !== undefined) {
      $("distinct").textContent = body.distinct === null ? "–" : `${body.distinct} / ${body.signed}`;
    }
    if (body.queued !== undefined) $("queued").textContent = body.queued;
    if (body.answered !== undefined) $("answers-all").textContent = body.answered;
    if (body.answered_by_you !== undefined) $("answers-mine").textContent = body.answered_by_you;
    else if (body.per_annotator) $("answers-mine").textContent = body.per_annotator[annotator] || 0;
    if (body.your_median_s !== undefined) {
      $("median-mine").textContent = body.your_median_s === null ? "–" : body.your_median_s.toFixed(1) + " s";
    }
    if (body.reply_window_s) windowS = body.reply_window_s;
  }

  function enableButtons(on) {
    document.querySelectorAll(".buttons button").forEach((b) => { b.disabled = !on; });
    if (on) $("btn-found").disabled = !(current && current.images.goal1_found && current.images.goal2_found);
  }

  function clearQuestion() {
    current = null;
    deadline = 0;
    showingFound = false;
    $("question").dataset.queryId = "";
    $("question").dataset.state = "idle";
    enableButtons(false);
    for (const kind of KINDS) $("img-" + kind).removeAttribute("src");
    for (const id of ["goal1-id", "goal2-id", "goal1-name", "goal2-name"]) $(id).textContent = "";
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
    await showOrWait(result.body.query);
  }

  async function showOrWait(query) {
    if (!query) {
      setStatus("No question waiting; the next one appears here by itself.");
      schedule(1000);
      return;
    }
    await show(query);
  }

  function imageUrl(query, kind) {
    const found = showingFound && kind !== "state" ? query.images[kind + "_found"] : null;
    return found || query.images[kind];
  }

  async function setImages(query) {
    const loads = [];
    for (const kind of KINDS) {
      const img = $("img-" + kind);
      const url = imageUrl(query, kind);
      if (url) {
        img.src = HHP.withToken(url);
        loads.push(img.decode().catch(() => null));
      } else {
        img.removeAttribute("src");
      }
    }
    await Promise.all(loads);
  }

  async function show(query) {
    current = query;
    showingFound = false;
    $("question").dataset.queryId = query.query_id;
    $("question").dataset.state = "loading";
    $("goal1-id").textContent = "#" + query.goal1;
    $("goal2-id").textContent = "#" + query.goal2;
    $("goal1-name").textContent = query.goal1_name;
    $("goal2-name").textContent = query.goal2_name;
    await setImages(query);          // the countdown starts once the images are visible
    if (current !== query) return;
    enableButtons(true);
    setStatus(query.drawn_in_state
      ? "Both sub-goals are drawn in the current room: which one should the agent reach next?"
      : "In the current state, which sub-goal is better?");
    shownAt = performance.now();
    $("question").dataset.shownAt = shownAt.toFixed(1);
    $("question").dataset.state = "ready";
    deadline = shownAt + windowS * 1000;
    tick();
  }

  async function toggleFound() {
    if (!current || !current.images.goal1_found || !current.images.goal2_found) return;
    showingFound = !showingFound;
    $("btn-found").classList.toggle("on", showingFound);
    await setImages(current);
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
    const responseS = timedOut ? null : Math.max(0, (performance.now() - shownAt) / 1000);
    busy = true;
    deadline = 0;
    enableButtons(false);
    let result;
    try {
      result = await HHP.api("/api/answer", {
        method: "POST",
        headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ query_id: query.query_id, label, annotator, response_s: responseS, next: true }),
      });
    } catch (e) {
      busy = false;
      setStatus("Cannot reach the server; answer again.");
      enableButtons(true);
      return;
    }
    busy = false;
    const item = document.createElement("li");
    const pair = `${query.goal1_name} vs ${query.goal2_name}`;
    if (result.ok) {
      setCounts(result.body);
      item.textContent = `${pair}: ${LABEL_TEXT[label]}` + (timedOut ? " (time ran out)" : "");
    } else if (result.status === 409 || result.status === 404) {
      item.textContent = `${pair}: answered by someone else`;
    } else {
      setStatus("The server refused the answer (" + result.status + "): " + JSON.stringify(result.body));
      enableButtons(true);
      return;
    }
    $("history").prepend(item);
    clearQuestion();
    if (result.ok && result.body.next !== undefined) await showOrWait(result.body.next);
    else fetchNext();
  }

  function start() {
    const name = $("annotator").value.trim();
    if (!name) { setStatus("Type your name above and press Enter to start."); return; }
    if (name === annotator) return;
    annotator = name;
    try { localStorage.setItem("sb3_hhp.annotator", name); } catch (e) { /* private mode */ }
    $("answers-mine").textContent = "0";
    $("median-mine").textContent = "–";
    clearQuestion();
    fetchNext();
  }

  document.addEventListener("keydown", (event) => {
    if (event.target === $("annotator")) {
      if (event.key === "Enter") { $("annotator").blur(); start(); }
      return;
    }
    if ((event.key === "e" || event.key === "E") && current) { event.preventDefault(); toggleFound(); return; }
    const label = KEYS[event.key];
    if (label && current) { event.preventDefault(); submit(label); }
  });
  $("annotator").addEventListener("change", start);
  document.querySelectorAll(".buttons button[data-label]").forEach((button) => {
    button.addEventListener("click", () => submit(button.dataset.label));
  });
  $("btn-found").addEventListener("click", toggleFound);
  $("gallery-link").href = HHP.withToken("/gallery");

  // Keep the counts fresh while a question is shown.
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
