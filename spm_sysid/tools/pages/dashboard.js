// The live dashboard: asks the node for /state.json every POLL_MS milliseconds and redraws
// in place. window.spmDashboard holds the last state received and how many were drawn.
(function () {
  "use strict";
  var POLL_MS = $poll_ms;
  var token = new URLSearchParams(window.location.search).get("token") || "";
  var query = token ? "?token=" + encodeURIComponent(token) : "";
  var board = window.spmDashboard = { state: null, updates: 0, errors: 0 };
  var modelId = null;
  function text(id, value) { document.getElementById(id).textContent = value; }
  function fmt(v, d) { return (v === null || v === undefined || isNaN(v)) ? "-" :
                       Number(v).toPrecision(d || 4); }
  function clock(date) {  // 24 h, as the node's times
    function two(n) { return (n < 10 ? "0" : "") + n; }
    return two(date.getHours()) + ":" + two(date.getMinutes()) + ":" + two(date.getSeconds());
  }
  function canvases(name) {
    var id = "plot-" + name, c = document.getElementById(id);
    if (!c) {
      var h = document.createElement("h3"); h.textContent = name;
      c = document.createElement("canvas"); c.id = id; c.className = "signals";
      c.dataset.output = name;
      var r = document.createElement("canvas"); r.id = "residual-" + name;
      r.className = "residual"; r.dataset.output = name;
      var box = document.getElementById("plots");
      box.appendChild(h); box.appendChild(c); box.appendChild(r);
    }
    return [c, document.getElementById("residual-" + name)];
  }
  function niceStep(span, count) {  // 1, 2 or 5 times a power of ten
    var raw = span / count, p = Math.pow(10, Math.floor(Math.log10(raw)));
    return [1, 2, 5, 10].map(function (m) { return m * p; })
      .find(function (s) { return s >= raw; });
  }
  function prepare(c) {
    var w = c.clientWidth || 800, h = c.clientHeight || 200;
    if (c.width !== w) { c.width = w; } if (c.height !== h) { c.height = h; }
    var g = c.getContext("2d"); g.clearRect(0, 0, w, h);
    g.font = "11px sans-serif";
    return [g, w, h];
  }
  function range(series) {
    var lo = Infinity, hi = -Infinity;
    series.forEach(function (ys) { ys.forEach(function (v) {
      if (v !== null && isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); } }); });
    if (!(hi > lo)) { hi = (isFinite(lo) ? lo : 0) + 1; lo = hi - 2; }
    var pad = 0.05 * (hi - lo);
    return [lo - pad, hi + pad];
  }
  function plot(c, t, series, styles, withTimeAxis) {
    var gwh = prepare(c), g = gwh[0], w = gwh[1], h = gwh[2], n = t.length;
    var left = 60, right = 10, top = 8, bottom = withTimeAxis ? 22 : 8;
    if (!n) { return; }
    var yr = range(series), t0 = t[0], t1 = t[n - 1] > t0 ? t[n - 1] : t0 + 1, i;
    function X(v) { return left + (w - left - right) * (v - t0) / (t1 - t0); }
    function Y(v) { return h - bottom - (h - top - bottom) * (v - yr[0]) / (yr[1] - yr[0]); }
    g.strokeStyle = "#eee"; g.fillStyle = "#555"; g.lineWidth = 1;
    var ys = niceStep(yr[1] - yr[0], 4);  // value grid and labels
    for (var v = Math.ceil(yr[0] / ys) * ys; v <= yr[1]; v += ys) {
      g.beginPath(); g.moveTo(left, Y(v)); g.lineTo(w - right, Y(v)); g.stroke();
      g.fillText(fmt(Math.abs(v) < ys / 1e6 ? 0 : v, 3), 2, Y(v) + 4);
    }
    var ts = niceStep(t1 - t0, 8);  // time grid: seconds before the newest sample
    for (var s = Math.ceil(t0 / ts) * ts; s <= t1 + 1e-9; s += ts) {
      g.beginPath(); g.moveTo(X(s), top); g.lineTo(X(s), h - bottom); g.stroke();
      if (withTimeAxis) {
        var label = Math.abs(s) < ts / 1e6 ? "0 s (now)" : fmt(s, 3) + " s";
        g.fillText(label, Math.min(X(s) - 10, w - right - 50), h - 6);
      }
    }
    series.forEach(function (values, k) {
      var st = styles[k], up = false;
      g.strokeStyle = st.color; g.lineWidth = st.width;
      g.setLineDash(st.dash || []); g.beginPath();
      for (i = 0; i < n; i++) {
        if (values[i] === null || !isFinite(values[i])) { up = false; continue; }
        if (up) { g.lineTo(X(t[i]), Y(values[i])); } else { g.moveTo(X(t[i]), Y(values[i])); }
        up = true;
      }
      g.stroke(); g.setLineDash([]);
    });
  }
  function draw(name, s) {
    var cs = canvases(name);
    var residual = s.measured.map(function (m, i) {
      var p = s.predicted[i];
      return (m === null || p === null) ? null : m - p; });
    plot(cs[0], s.t, [s.measured, s.predicted],
         [{ color: "#1f3b73", width: 1.5 }, { color: "#e8730c", width: 1.5, dash: [5, 3] }],
         false);
    plot(cs[1], s.t, [residual], [{ color: "#777", width: 1 }], true);
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
  function showState(mon) {
    var el = document.getElementById("state"), waiting = mon.state === "VALID" &&
      !mon.samples;
    // a model with no sample monitored yet is not "valid": nothing has been checked
    el.textContent = waiting ? "WAITING FOR SAMPLES" : mon.state.replace("_", " ");
    el.className = waiting ? "WAITING" : mon.state;
    text("reason", waiting ? "the model is set; no sample has been predicted yet" :
         (mon.reason || ""));
    text("since", mon.since || "-");
  }
  function threshold(st) {
    var low = Object.keys(st.outputs).filter(function (k) {
      var p = st.outputs[k].stats.whiteness_p; return p !== null && p < 0.05; });
    text("threshold", st.monitor.state === "VALID" && low.length ?
      "Why VALID with a whiteness p below 0.05: the monitor does not use a fixed p-value. " +
      "Each window is compared with the identification's own residuals (their worst " +
      "window's Ljung-Box Q and RMS ratio, with 5 % margin); residuals that were as " +
      "coloured when the model was fitted are no change." : "");
  }
  function update(st) {
    board.state = st; board.updates += 1;
    text("node", st.node); text("seconds", fmt(st.seconds, 3));
    showState(st.monitor);
    text("updated", "updated " + clock(new Date()) + ", " + st.monitor.samples +
         " samples monitored");
    threshold(st);
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
      draw(name, s);
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
