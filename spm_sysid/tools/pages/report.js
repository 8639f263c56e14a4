// The report's plots: draws every figure spec (the page's JSON) with BokehJS's own API and
// keeps the data sources by name in window.spmReport.sources (for a reader, or a test).
(function () {
  "use strict";
  var specs = JSON.parse(document.getElementById("spm-plots").textContent);
  var R = window.spmReport = { sources: {}, figures: {}, ready: false, errors: [] };
  function column(values) { return values.map(function (v) { return v === null ? NaN : v; }); }
  var shown = [], groups = {}, order = [];
  specs.forEach(function (spec) {
    try {
      // the toolbar above the plot: beside a small plot it would fold into "..."
      var args = { title: spec.title, height: spec.height, sizing_mode: "stretch_width",
                   tools: "pan,box_zoom,wheel_zoom,reset", x_axis_label: spec.x_label,
                   y_axis_label: spec.y_label, toolbar_location: "above" };
      if (spec.link_x && R.figures[spec.link_x]) { args.x_range = R.figures[spec.link_x].x_range; }
      if (spec.y_range) {  // the signals' range: a wide band must not flatten them
        args.y_range = new Bokeh.Range1d({ start: spec.y_range[0], end: spec.y_range[1] });
      }
      var p = Bokeh.Plotting.figure(args);
      p.toolbar.logo = null;
      if (spec.glyphs.some(function (g) { return g.legend; })) {
        // the legend above the plot, in a row: inside it would cover the curves
        var legend = new Bokeh.Legend({ orientation: "horizontal", location: "top_left",
                                        click_policy: "hide", label_text_font_size: "11px",
                                        padding: 2, margin: 0, spacing: 12 });
        p.add_layout(legend, "above");
      }
      Object.keys(spec.sources).forEach(function (name) {
        var data = {};
        Object.keys(spec.sources[name]).forEach(function (k) {
          data[k] = column(spec.sources[name][k]); });
        R.sources[name] = new Bokeh.ColumnDataSource({ data: data, name: name });
      });
      spec.glyphs.forEach(function (g) {
        var src = R.sources[g.source], opts = { source: src };
        if (g.legend) { opts.legend_label = g.legend; }
        if (g.type === "line") {
          opts.line_color = g.color; opts.line_width = g.width;
          if (g.dash) { opts.line_dash = g.dash; }
          p.line({ field: g.x }, { field: g.y }, opts);
        } else if (g.type === "varea") {
          opts.fill_color = g.color; opts.fill_alpha = g.alpha;
          opts.x = { field: g.x }; opts.y1 = { field: g.y1 }; opts.y2 = { field: g.y2 };
          p.varea(opts);
        } else if (g.type === "scatter") {
          opts.size = g.size; opts.fill_color = g.color; opts.line_color = g.color;
          p.scatter({ field: g.x }, { field: g.y }, opts);
        } else if (g.type === "segment") {
          opts.line_color = g.color; opts.line_width = g.width;
          opts.x0 = { field: g.x }; opts.y0 = 0; opts.x1 = { field: g.x };
          opts.y1 = { field: g.y };
          p.segment(opts);
        }
      });
      spec.spans.forEach(function (level) {
        p.add_layout(new Bokeh.Span({ location: level, dimension: "width",
                                      line_color: "#d62728", line_dash: "dashed" }));
      });
      R.figures[spec.id] = p;
      if (spec.link_x && R.figures[spec.link_x]) { groups[spec.link_x].push(p); }
      else { groups[spec.id] = [p]; order.push(spec.id); }
    } catch (e) {
      R.errors.push(spec.id + ": " + e);
      document.getElementById(spec.id).textContent = "this plot could not be drawn (" + e + ")";
    }
  });
  // figures that share an x range are drawn together (one document each group)
  order.forEach(function (id) {
    try {
      // a grid even of one figure: its toolbar gets a row of its own above the titles
      // (beside a title in the figure's own row it folds into "...")
      var root = Bokeh.Plotting.gridplot(
        groups[id].map(function (f) { return [f]; }), { sizing_mode: "stretch_width",
                                                        toolbar_location: "above" });
      shown.push(Bokeh.Plotting.show(root, "#" + id));
    } catch (e) { R.errors.push(id + ": " + e); }
  });
  Promise.all(shown).then(function () { R.ready = true; },
                          function (e) { R.errors.push(String(e)); R.ready = true; });
})();
