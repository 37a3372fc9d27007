// The sub-goal gallery: every sub-goal's image and statistics, refreshed every few seconds.
"use strict";

(() => {
  const REFRESH_MS = 4000;
  const $ = (id) => document.getElementById(id);
  const fmt = (value, digits) => (value === null || value === undefined ? "–" : Number(value).toFixed(digits));

  function card(record, stamp) {
    const figure = document.createElement("figure");
    figure.className = "subgoal";
    figure.dataset.subgoalId = record.id;
    const img = document.createElement("img");
    img.src = HHP.withToken(record.image + "?r=" + stamp);
    img.alt = record.name ? record.name : "sub-goal " + record.id;
    const caption = document.createElement("figcaption");
    const success = record.success_rate === null ? "–" : (100 * record.success_rate).toFixed(0) + " %";
    const name = document.createElement("span");
    name.className = "name";
    name.textContent = record.name || "(no name)";
    const line = document.createElement("span");
    line.textContent =
      `#${record.id} found at step ${record.found_at === null ? "–" : record.found_at} · ` +
      `success ${success} · chosen ${record.chosen_recently} · score ${fmt(record.mean_score, 3)}`;
    caption.append(name, line);
    figure.append(caption, img);
    return figure;
  }

  async function refresh() {
    try {
      const result = await HHP.api("/api/subgoals");
      if (result.status === 401) { $("status").textContent = "Wrong or missing token."; return; }
      if (!result.ok) { $("status").textContent = "Server error " + result.status; return; }
      const records = result.body.subgoals;
      const stamp = Math.round(result.body.time * 1000);
      $("count").textContent = records.length;
      $("status").textContent = records.length ? "" : "No sub-goal yet.";
      $("gallery").replaceChildren(...records.map((r) => card(r, stamp)));
      $("updated").textContent = "updated " + new Date().toLocaleTimeString();
    } catch (e) {
      $("status").textContent = "Cannot reach the server; retrying…";
    }
  }

  $("label-link").href = HHP.withToken("/");
  refresh();
  setInterval(refresh, REFRESH_MS);
})();
