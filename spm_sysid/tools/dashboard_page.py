"""The live dashboard's page: one HTML file, its script inlined, no library, no network.

The node serves it (:mod:`spm_sysid.ros.node.dashboard`) at ``/`` and the data
at ``/state.json``; the page asks for the data four times a second and redraws
in place (no reload): the monitor's state with its reason and the time it
changed, measured against predicted for the last seconds (one canvas per
output), the residual statistics, the model in use with its coefficient table,
an identification's progress while it runs, and a link to the last
identification's report. It has no button that changes anything.

The plots are drawn on a ``<canvas>`` by the page's own few lines: a live view
needs lines, not a plotting library. ``window.spmDashboard`` holds the last
state the page received (``state``) and how many it has drawn (``updates``),
for a reader or a test to check what the page shows.
"""

from __future__ import annotations

__all__ = ["PAGE", "page"]

#: Polling period of the page, milliseconds.
POLL_MS = 250

PAGE = """<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>spm_sysid live</title>
<style>
body { font-family: system-ui, sans-serif; margin: 1em auto; max-width: 1100px; padding: 0 1em;
       color: #222; }
#state { display: inline-block; padding: .3em .8em; border-radius: .3em; color: white;
         font-weight: bold; font-size: 130%; }
.VALID { background: #2a8a2a; } .DEGRADED { background: #d98c00; }
.INVALID { background: #c02020; } .NO_MODEL { background: #777; }
.equation { font-family: ui-monospace, monospace; background: #f4f4f4; padding: .4em;
            overflow-x: auto; }
table { border-collapse: collapse; font-size: 90%; }
td, th { border-bottom: 1px solid #ddd; padding: .15em .7em; text-align: right; }
td.term { text-align: left; font-family: ui-monospace, monospace; }
canvas { width: 100%; height: 220px; border: 1px solid #ddd; }
.small { font-size: 85%; color: #555; }
#error { color: #c02020; }
</style></head>
<body>
<h1>spm_sysid <span id="node"></span></h1>
<p><span id="state" class="NO_MODEL">NO_MODEL</span> <span id="reason"></span></p>
<p class="small">state since <span id="since">-</span>; <span id="updated">waiting for the
node</span>; read-only view, nothing here changes the node or the robot.
<span id="error"></span></p>
<div id="progress"></div>
<h2>Measured and predicted, last <span id="seconds"></span> s</h2>
<div id="plots"></div>
<h2>Residuals</h2>
<table id="residuals"><tr><th>output</th><th>samples</th><th>mean</th><th>RMS</th>
<th>RMS / identification's</th><th>whiteness p</th></tr></table>
<h2>Model in use</h2>
<div id="model"><p>no model yet</p></div>
<p id="report"></p>
<script>
(function () {
  "use strict";
  var token = new URLSearchParams(window.location.search).get("token") || "";
  var query = token ? "?token=" + encodeURIComponent(token) : "";
  var board = window.spmDashboard = { state: null, updates: 0, errors: 0 };
  var modelId = null;
  function text(id, value) { document.getElementById(id).textContent = value; }
  function fmt(v, d) { return (v === null || v === undefined || isNaN(v)) ? "-" :
                       Number(v).toPrecision(d || 4); }
  function canvasFor(name) {
    var id = "plot-" + name, c = document.getElementById(id);
    if (!c) {
      var h = document.createElement("h3"); h.textContent = name;
      c = document.createElement("canvas"); c.id = id; c.dataset.output = name;
      document.getElementById("plots").appendChild(h);
      document.getElementById("plots").appendChild(c);
    }
    return c;
  }
  function draw(c, s) {
    var w = c.clientWidth || 800, h = c.clientHeight || 220;
    if (c.width !== w) { c.width = w; } if (c.height !== h) { c.height = h; }
    var g = c.getContext("2d"); g.clearRect(0, 0, w, h);
    var n = s.t.length; if (!n) { return; }
    var lo = Infinity, hi = -Infinity, i;
    for (i = 0; i < n; i++) {
      [s.measured[i], s.predicted[i]].forEach(function (v) {
        if (v !== null && isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); } });
    }
    if (!(hi > lo)) { hi = lo + 1; lo = lo - 1; }
    var t0 = s.t[0], t1 = s.t[n - 1] > t0 ? s.t[n - 1] : t0 + 1, pad = 30;
    function X(t) { return pad + (w - 2 * pad) * (t - t0) / (t1 - t0); }
    function Y(v) { return h - 20 - (h - 40) * (v - lo) / (hi - lo); }
    g.fillStyle = "#555"; g.font = "11px sans-serif";
    g.fillText(fmt(hi, 3), 2, 12); g.fillText(fmt(lo, 3), 2, h - 22);
    g.fillText("-" + fmt(t1 - t0, 3) + " s", pad, h - 4); g.fillText("now", w - pad - 20, h - 4);
    [["measured", "#000"], ["predicted", "#d62728"]].forEach(function (line) {
      var ys = s[line[0]], up = false;
      g.strokeStyle = line[1]; g.lineWidth = 1; g.beginPath();
      for (i = 0; i < n; i++) {
        if (ys[i] === null || !isFinite(ys[i])) { up = false; continue; }
        if (up) { g.lineTo(X(s.t[i]), Y(ys[i])); } else { g.moveTo(X(s.t[i]), Y(ys[i])); }
        up = true;
      }
      g.stroke();
      g.fillStyle = line[1]; g.fillText(line[0], w - 90, line[0] === "measured" ? 12 : 26);
    });
  }
  function table(m) {
    var rows = ["<tr><th>term</th><th>coefficient</th><th>std. error</th></tr>"];
    m.terms.forEach(function (term, j) {
      var se = m.standard_errors ? m.standard_errors[j] : null;
      rows.push("<tr><td class='term'></td><td data-value='" + m.coefficients[j] + "'>" +
                fmt(m.coefficients[j], 6) + "</td><td>" + fmt(se, 3) + "</td></tr>");
    });
    var t = document.createElement("table"); t.className = "coefficients";
    t.dataset.output = m.output; t.innerHTML = rows.join("");
    var cells = t.querySelectorAll("td.term");
    m.terms.forEach(function (term, j) { cells[j].textContent = term; });
    return t;
  }
  function showModel(model) {
    var box = document.getElementById("model");
    if (!model) { box.innerHTML = "<p>no model yet</p>"; modelId = null; return; }
    if (model.id === modelId) { return; }
    modelId = model.id; box.innerHTML = "";
    var p = document.createElement("p"); p.className = "small";
    p.textContent = model.summary; box.appendChild(p);
    model.outputs.forEach(function (m) {
      var e = document.createElement("p"); e.className = "equation";
      e.textContent = m.equation; box.appendChild(e); box.appendChild(table(m));
    });
  }
  function update(st) {
    board.state = st; board.updates += 1;
    text("node", st.node); text("seconds", fmt(st.seconds, 3));
    var el = document.getElementById("state");
    el.textContent = st.monitor.state; el.className = st.monitor.state;
    text("reason", st.monitor.reason || "");
    text("since", st.monitor.since || "-");
    text("updated", "updated " + new Date().toLocaleTimeString() + ", " +
         st.monitor.samples + " samples monitored");
    var pr = document.getElementById("progress");
    pr.textContent = st.progress ? ("identifying: " + st.progress.phase +
      (st.progress.total ? " " + st.progress.step + "/" + st.progress.total : "") +
      (st.progress.best !== null ? ", best " + fmt(st.progress.best, 6) : "") +
      ", " + fmt(st.progress.elapsed, 3) + " s") :
      (st.last_identification ? "last identification: " + st.last_identification : "");
    var res = document.getElementById("residuals");
    while (res.rows.length > 1) { res.deleteRow(1); }
    Object.keys(st.outputs).forEach(function (name) {
      var s = st.outputs[name], r = res.insertRow();
      [name, s.stats.samples, fmt(s.stats.mean), fmt(s.stats.rms), fmt(s.stats.rms_ratio),
       fmt(s.stats.whiteness_p)].forEach(function (v) { r.insertCell().textContent = v; });
      draw(canvasFor(name), s);
    });
    showModel(st.model);
    var rep = document.getElementById("report");
    if (st.report) {
      rep.innerHTML = "";
      var a = document.createElement("a"); a.href = st.report + query; a.id = "report-link";
      a.textContent = "the last identification's report"; a.target = "_blank";
      rep.appendChild(a);
    }
  }
  function poll() {
    fetch("state.json" + query, { cache: "no-store" }).then(function (r) {
      if (!r.ok) { throw new Error(r.status + " " + r.statusText); }
      return r.json();
    }).then(function (st) { text("error", ""); update(st); }).catch(function (e) {
      board.errors += 1; text("error", "no answer from the node (" + e.message + ")");
    }).finally(function () { window.setTimeout(poll, POLL_MS); });
  }
  poll();
})();
</script>
</body></html>
"""


def page() -> str:
    """The page's HTML."""
    return PAGE.replace("POLL_MS", str(POLL_MS))
