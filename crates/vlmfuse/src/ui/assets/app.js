// vlmfuse operator page: vanilla JS, no build step, no external resources.
// Everything that comes from the API is written with textContent / setAttribute, never as HTML.
"use strict";
(() => {
  const $ = (id) => document.getElementById(id);

  // ---- login page: only show the error after a failed attempt ----
  if ($("login")) {
    if (new URLSearchParams(location.search).get("login") === "failed") {
      const e = $("login-error");
      if (e) e.hidden = false;
    }
    return;
  }

  const SVGNS = "http://www.w3.org/2000/svg";
  const PALETTE = ["#0072B2", "#E69F00", "#009E73", "#CC79A7", "#D55E00", "#56B4E9", "#7A7A7A", "#222222"];
  const PRED = { model: "#0072B2", vote: "#E69F00" };
  const meta = document.querySelector('meta[name="vlmfuse-poll-ms"]');
  const POLL_MS = Math.max(250, parseInt(meta && meta.content, 10) || 2000);
  const PAGE = 20;

  // ---- DOM helpers ----
  function put(e, attrs, kids) {
    if (attrs) {
      for (const k of Object.keys(attrs)) {
        const v = attrs[k];
        if (v === null || v === undefined) continue;
        if (k === "text") e.textContent = v;
        else if (k === "style") e.style.cssText = v; // CSSOM, so a CSP without 'unsafe-inline' allows it
        else if (k.startsWith("on")) e.addEventListener(k.slice(2), v);
        else e.setAttribute(k, String(v));
      }
    }
    for (const c of kids.flat(Infinity)) {
      if (c === null || c === undefined || c === false) continue;
      e.append(c instanceof Node ? c : String(c));
    }
    return e;
  }
  const h = (tag, attrs, ...kids) => put(document.createElement(tag), attrs, kids);
  const s = (tag, attrs, ...kids) => put(document.createElementNS(SVGNS, tag), attrs, kids);

  const isNum = (x) => typeof x === "number" && Number.isFinite(x);
  const fmt = (x, d = 2) => (isNum(x) ? x.toFixed(d).replace(/^-(0\.?0*)$/, "$1") : "–");
  const fmtMs = (x) => (isNum(x) ? (x >= 100 ? x.toFixed(0) : x.toFixed(1)) : "–");
  const pad = (n) => String(n).padStart(2, "0");
  function fmtTime(ms, short) {
    if (!isNum(ms)) return "–";
    const d = new Date(ms);
    const t = `${pad(d.getHours())}:${pad(d.getMinutes())}:${pad(d.getSeconds())}`;
    return short ? t : `${d.getFullYear()}-${pad(d.getMonth() + 1)}-${pad(d.getDate())} ${t}`;
  }
  function setVal(id, v, text) {
    const e = $(id);
    if (!e) return;
    e.dataset.value = String(v);
    e.textContent = text !== undefined ? text : v === null || v === undefined ? "–" : String(v);
  }
  const setReady = (id) => { $(id).dataset.ready = "true"; };
  const memo = {};
  function changed(key, value) {
    const k = JSON.stringify(value);
    if (memo[key] === k) return false;
    memo[key] = k;
    return true;
  }
  let summary = null;
  const reportersOf = (sm) => (sm && Array.isArray(sm.reporters) ? sm.reporters : sm ? Object.keys(sm.state.reputations || {}) : []);
  function colorOf(name) {
    const i = reportersOf(summary).indexOf(name);
    return PALETTE[(i < 0 ? 7 : i) % PALETTE.length];
  }
  const labelName = (id) => {
    const l = summary && (summary.labels || []).find((x) => x.id === id);
    return l ? l.name : id;
  };
  const chips = (ids) => h("span", { class: "chips" }, (ids || []).map((id) => h("span", { class: "chip", "data-label": id, title: labelName(id) }, id)));
  const swatch = (c) => h("span", { class: "swatch", style: `background:${c}` });
  const none = (t) => h("span", { class: "muted" }, t || "–");

  // ---- banner and errors ----
  function showBanner(msg, kind) {
    const b = $("banner");
    if (b.dataset.kind === "script" && kind !== "script") return; // keep script errors visible
    b.dataset.kind = kind;
    b.textContent = msg;
    b.hidden = false;
  }
  function clearBanner() {
    const b = $("banner");
    if (b.dataset.kind === "script") return;
    b.hidden = true;
    b.textContent = "";
    delete b.dataset.kind;
  }
  window.addEventListener("error", (e) => showBanner(`Script error: ${e.message}`, "script"));
  window.addEventListener("unhandledrejection", (e) => showBanner(`Script error: ${e.reason && e.reason.message ? e.reason.message : e.reason}`, "script"));
  function setLive(state, text) {
    const e = $("live");
    e.dataset.state = state;
    e.textContent = text || state;
  }

  class HttpError extends Error {
    constructor(status, message, kind) {
      super(message);
      this.status = status;
      this.kind = kind;
    }
  }
  let reloading = false, gaveUp = false;
  function expired() {
    // The cookie expired: reloading makes the server serve the login page. Guard against a
    // reload loop if the server keeps answering 401 while still serving this page.
    if (reloading) return;
    const last = Number(sessionStorage.getItem("vlmfuse-401") || 0);
    if (gaveUp || Date.now() - last < 10000) {
      gaveUp = true;
      showBanner("Not authorised (401). Reload the page to log in again.", "fetch");
      return;
    }
    reloading = true;
    sessionStorage.setItem("vlmfuse-401", String(Date.now()));
    location.reload();
  }
  async function api(url, opts) {
    let res;
    try {
      res = await fetch(url, Object.assign({ credentials: "same-origin", cache: "no-store", headers: { Accept: "application/json" } }, opts || {}));
    } catch (e) {
      throw new HttpError(0, `Cannot reach the server (${url}): ${e.message}`, "network");
    }
    if (res.status === 401) {
      expired();
      throw new HttpError(401, "Session expired; reloading", "unauthorized");
    }
    const text = await res.text();
    let body = null;
    try { body = text ? JSON.parse(text) : null; } catch (_) { body = null; }
    if (!res.ok) throw new HttpError(res.status, (body && body.error) || `HTTP ${res.status} ${res.statusText} (${url})`, body && body.kind);
    if (body === null) throw new HttpError(res.status, `Not JSON from ${url}`, "bad_response");
    return body;
  }

  // ---- SVG axes ----
  function nice(lo, hi, n) {
    if (!(hi > lo)) hi = lo + 1;
    const raw = (hi - lo) / n;
    const p = 10 ** Math.floor(Math.log10(raw));
    const m = raw / p;
    const step = (m < 1.5 ? 1 : m < 3 ? 2 : m < 7 ? 5 : 10) * p;
    const ticks = [];
    for (let v = Math.ceil(lo / step - 1e-9) * step; v <= hi + step * 1e-9; v += step) ticks.push(+v.toFixed(10));
    return { step, ticks };
  }
  const tickText = (v, step) => v.toFixed(Math.max(0, -Math.floor(Math.log10(step) + 1e-9)));
  // Draws grid, axes, ticks and axis titles into svg; returns the scale functions.
  function frame(svg, g, x0, x1, y0, y1, xTitle, yTitle) {
    const { W, H, M } = g;
    const xs = (x) => M.l + ((x - x0) / (x1 - x0 || 1)) * (W - M.l - M.r);
    const ys = (y) => H - M.b - ((y - y0) / (y1 - y0 || 1)) * (H - M.t - M.b);
    const xt = nice(x0, x1, g.xn || 6), yt = nice(y0, y1, g.yn || 5);
    for (const v of yt.ticks) {
      svg.append(s("line", { class: "grid", x1: M.l, x2: W - M.r, y1: ys(v), y2: ys(v) }));
      svg.append(s("text", { class: "tick", x: M.l - 5, y: ys(v) + 3.5, "text-anchor": "end" }, tickText(v, yt.step)));
    }
    for (const v of xt.ticks) {
      svg.append(s("line", { class: "axis", x1: xs(v), x2: xs(v), y1: H - M.b, y2: H - M.b + 4 }));
      svg.append(s("text", { class: "tick", x: xs(v), y: H - M.b + 15, "text-anchor": "middle" }, tickText(v, xt.step)));
    }
    svg.append(s("line", { class: "axis", x1: M.l, x2: W - M.r, y1: H - M.b, y2: H - M.b }));
    svg.append(s("line", { class: "axis", x1: M.l, x2: M.l, y1: M.t, y2: H - M.b }));
    svg.append(s("text", { class: "axis-title", x: (M.l + W - M.r) / 2, y: H - 4, "text-anchor": "middle" }, xTitle));
    svg.append(s("text", { class: "axis-title", x: 0, y: 0, "text-anchor": "middle", transform: `translate(11 ${(M.t + H - M.b) / 2}) rotate(-90)` }, yTitle));
    return { xs, ys };
  }

  // ---- header ----
  function renderHeader(sm) {
    const st = sm.state || {};
    setVal("method", st.method);
    setVal("rounds-stored", st.rounds);
    setVal("labelled-rounds", st.labelled_rounds);
    setVal("last-update", sm.generated_ms, fmtTime(sm.generated_ms, true));
    $("last-update").title = fmtTime(sm.generated_ms);
  }

  // ---- panel 1: reputations ----
  function renderReputations(sm) {
    const reps = reportersOf(sm);
    const pts = (sm.reputation_history && sm.reputation_history.points) || [];
    const drift = (sm.drift && sm.drift.reporters) || [];
    const dmap = new Map(drift.map((d) => [d.reporter, d]));
    if (changed("rep-chart", [reps, pts, drift])) drawReputationChart(reps, pts, drift, dmap);
    const st = sm.state || {};
    if (changed("rep-table", [reps, st.reputations, st.reporters, drift, sm.drift && sm.drift.window, sm.drift && sm.drift.threshold])) {
      const cell = (name, field, v, text) => h("td", { class: "num", "data-reporter": name, "data-field": field, "data-value": v === undefined ? "null" : String(v) }, text);
      const rows = reps.map((name) => {
        const r = (st.reporters || {})[name] || {};
        const d = dmap.get(name) || {};
        const rep = (st.reputations || {})[name];
        return h("tr", { class: d.alarm ? "in-alarm" : null },
          h("th", { scope: "row" }, swatch(colorOf(name)), name),
          cell(name, "reputation", rep, fmt(rep, 3)),
          cell(name, "rounds_credited", r.rounds_credited, isNum(r.rounds_credited) ? String(r.rounds_credited) : "–"),
          cell(name, "last_phi", r.last_phi, fmt(r.last_phi, 3)),
          cell(name, "recent", d.recent, fmt(d.recent, 3)),
          cell(name, "previous", d.previous, fmt(d.previous, 3)),
          cell(name, "drop", d.drop, fmt(d.drop, 3)),
          h("td", { "data-reporter": name, "data-field": "alarm", "data-value": String(!!d.alarm) },
            d.alarm ? h("span", { class: "alarm", title: "mean credit share dropped by more than the threshold" }, "alarm") : dmap.has(name) ? h("span", { class: "okay" }, "ok") : none()));
      });
      $("reputation-table").tBodies[0].replaceChildren(...rows);
      const dr = sm.drift || {};
      $("drift-note").textContent = isNum(dr.window)
        ? `Drift: mean credit share over the latest ${dr.window} labelled rounds (recent) against the ${dr.window} before (previous); an alarm is raised when the drop exceeds ${dr.threshold}.`
        : "";
    }
    setReady("panel-reputations");
  }

  function drawReputationChart(reps, pts, drift, dmap) {
    const root = $("reputation-chart");
    const legend = $("reputation-legend");
    const readout = $("reputation-readout");
    legend.replaceChildren(...reps.map((n) => h("span", { class: "key", "data-reporter": n }, swatch(colorOf(n)), n,
      dmap.get(n) && dmap.get(n).alarm ? h("span", { class: "alarm" }, "alarm") : null)),
    h("span", { class: "key" }, h("span", { class: "marker-key" }), "drift alarm raised"));
    if (!pts.length) {
      root.replaceChildren(h("p", { class: "empty" }, "No labelled rounds yet: the chart starts with the first feedback."));
      readout.textContent = "";
      return;
    }
    const g = { W: 640, H: 270, M: { l: 46, r: 14, t: 10, b: 38 } };
    const x0 = pts[0].labelled;
    const x1 = Math.max(pts[pts.length - 1].labelled, x0 + 1);
    let wmax = 0;
    for (const p of pts) for (const w of p.w || []) if (isNum(w) && w > wmax) wmax = w;
    const step = nice(0, (wmax || 1) * 1.1, 5).step;
    let y1 = Math.ceil(((wmax || 1) * 1.1) / step - 1e-9) * step;
    if (y1 > 1 && wmax <= 1) y1 = 1;
    const svg = s("svg", { viewBox: `0 0 ${g.W} ${g.H}`, role: "img", "aria-label": "reputation of each reporter over labelled rounds" });
    const { xs, ys } = frame(svg, g, x0, x1, 0, y1, "labelled rounds", "reputation");
    const xOf = (p) => xs(p.labelled);
    const nearest = (x) => {
      let lo = 0, hi = pts.length - 1;
      while (hi - lo > 1) { const mid = (lo + hi) >> 1; if (pts[mid].labelled < x) lo = mid; else hi = mid; }
      return Math.abs(pts[lo].labelled - x) <= Math.abs(pts[hi].labelled - x) ? pts[lo] : pts[hi];
    };
    reps.forEach((name, i) => {
      let d = "", pen = "M";
      for (const p of pts) {
        const w = p.w ? p.w[i] : null;
        if (!isNum(w)) { pen = "M"; continue; }
        d += `${pen}${xOf(p).toFixed(1)},${ys(w).toFixed(1)}`;
        pen = "L";
      }
      const alarm = dmap.get(name) && dmap.get(name).alarm;
      svg.append(s("path", { class: alarm ? "series in-alarm" : "series", d, stroke: colorOf(name), "data-reporter": name }));
    });
    for (const dr of drift) {
      const i = reps.indexOf(dr.reporter);
      for (const a of dr.alarm_at || []) {
        if (!isNum(a.labelled) || a.labelled < x0 || a.labelled > x1) continue;
        const p = nearest(a.labelled);
        const w = i >= 0 && p.w ? p.w[i] : null;
        const c = colorOf(dr.reporter);
        const x = xs(a.labelled);
        svg.append(s("line", { class: "alarm-line", x1: x, x2: x, y1: g.M.t, y2: g.H - g.M.b, stroke: c }));
        svg.append(s("circle", { class: "alarm-marker", cx: x, cy: isNum(w) ? ys(w) : g.M.t + 4, r: 5, stroke: c, "data-reporter": dr.reporter, "data-labelled": a.labelled },
          s("title", null, `${dr.reporter}: drift alarm at labelled round ${a.labelled}`)));
      }
    }
    const guide = s("line", { class: "guide", x1: 0, x2: 0, y1: g.M.t, y2: g.H - g.M.b, visibility: "hidden" });
    svg.append(guide);
    const hint = "Point at the chart to read the values.";
    readout.textContent = hint;
    const hit = s("rect", { class: "hit", x: g.M.l, y: g.M.t, width: g.W - g.M.l - g.M.r, height: g.H - g.M.t - g.M.b });
    hit.addEventListener("pointermove", (ev) => {
      const b = svg.getBoundingClientRect();
      const vx = ((ev.clientX - b.left) * g.W) / b.width;
      const p = nearest(x0 + ((vx - g.M.l) / (g.W - g.M.l - g.M.r)) * (x1 - x0));
      guide.setAttribute("x1", xOf(p));
      guide.setAttribute("x2", xOf(p));
      guide.setAttribute("visibility", "visible");
      readout.textContent = `labelled round ${p.labelled} (${p.round_id}): ` + reps.map((n, i) => `${n} ${fmt(p.w && p.w[i], 3)}`).join(" · ");
    });
    hit.addEventListener("pointerleave", () => { guide.setAttribute("visibility", "hidden"); readout.textContent = hint; });
    svg.append(hit);
    root.replaceChildren(svg);
  }

  // ---- panel 2: reliability ----
  let scope = "overall";
  const scopeSel = $("reliability-scope");
  scopeSel.addEventListener("change", () => { scope = scopeSel.value; if (summary) renderReliability(summary); });
  const mix = (a, b, t) => {
    const p = (c, i) => parseInt(c.slice(1 + 2 * i, 3 + 2 * i), 16);
    return `rgb(${[0, 1, 2].map((i) => Math.round(p(a, i) + (p(b, i) - p(a, i)) * t)).join(",")})`;
  };
  const HEAT = { tpr: ["#f3f5f7", "#17803d"], fpr: ["#f3f5f7", "#c62828"] };
  function renderReliability(sm) {
    const rel = sm.reliability || {};
    const recent = rel.recent || null;
    scopeSel.disabled = !recent;
    scopeSel.options[1].disabled = !recent;
    if (!recent && scope === "recent") scope = "overall";
    scopeSel.value = scope;
    const m = scope === "recent" ? recent : rel.overall;
    const reps = reportersOf(sm);
    const labels = (sm.labels || []).map((l) => l.id);
    if (!changed("rel", [scope, reps, labels, m])) return;
    $("reliability-rounds").textContent = m && isNum(m.rounds)
      ? `${m.rounds} ${scope === "recent" ? "latest rounds' scenes" : "labelled rounds"} counted`
      : "no data yet";
    for (const metric of ["tpr", "fpr"]) {
      const grid = m ? m[metric] : null;
      const counts = m ? m[metric === "tpr" ? "positives" : "negatives"] : null;
      const [c0, c1] = HEAT[metric];
      const head = h("tr", null, h("th", { class: "corner" }, "reporter \\ label"),
        labels.map((id) => h("th", { class: "rot", scope: "col", title: labelName(id) }, h("span", null, id))));
      const body = reps.map((name, i) => h("tr", null, h("th", { scope: "row" }, name), labels.map((id, k) => {
        const v = grid && grid[i] ? grid[i][k] : null;
        const n = counts && counts[i] ? counts[i][k] : undefined;
        const td = h("td", {
          class: isNum(v) ? "cell" : "cell null", "data-reporter": name, "data-label": id, "data-metric": metric,
          "data-value": isNum(v) ? String(v) : "null",
          title: `${name} · ${id}: ${metric.toUpperCase()} ${fmt(v)}` + (isNum(n) ? ` (${n} ${metric === "tpr" ? "positives" : "negatives"})` : ""),
        }, fmt(v));
        if (isNum(v)) {
          const t = Math.min(1, Math.max(0, v));
          td.style.background = mix(c0, c1, t);
          td.style.color = t > 0.55 ? "#fff" : "#1b1f24";
        }
        return td;
      })));
      const cap = h("caption", null, h("span", { class: "scale" }, "0 ", h("i", { style: `background:linear-gradient(90deg,${c0},${c1})` }), " 1"),
        " · – = no ", metric === "tpr" ? "positives" : "negatives", " seen");
      $(`reliability-${metric}`).replaceChildren(cap, h("thead", null, head), h("tbody", null, body));
    }
    setReady("panel-reliability");
  }

  // ---- panel 3: calibration and serving ----
  function renderCalibration(sm) {
    const cal = sm.calibration || {};
    const sv = sm.serving || {};
    const st = sm.state || {};
    if (changed("cal", cal)) {
      setVal("ece", cal.ece === undefined ? null : cal.ece, fmt(cal.ece, 3));
      setVal("calibration-window", cal.window);
      setVal("calibration-rounds", cal.rounds);
      setVal("calibration-pairs", cal.pairs);
      const g = { W: 320, H: 300, M: { l: 46, r: 12, t: 10, b: 38 }, xn: 5, yn: 5 };
      const svg = s("svg", { viewBox: `0 0 ${g.W} ${g.H}`, role: "img", "aria-label": "reliability diagram" });
      const { xs, ys } = frame(svg, g, 0, 1, 0, 1, "mean predicted probability", "observed frequency");
      svg.append(s("line", { class: "diagonal", x1: xs(0), y1: ys(0), x2: xs(1), y2: ys(1) }));
      const bins = (cal.bins || []).filter((b) => b && b.count > 0 && isNum(b.mean_q) && isNum(b.freq));
      const cmax = Math.max(1, ...bins.map((b) => b.count));
      for (const b of bins) {
        svg.append(s("rect", { class: "bin-bar", x: xs(b.lo) + 1, width: Math.max(0, xs(b.hi) - xs(b.lo) - 2), y: ys(b.freq), height: ys(0) - ys(b.freq) }));
      }
      for (const b of bins) {
        svg.append(s("circle", { class: "bin-dot", cx: xs(b.mean_q), cy: ys(b.freq), r: (3 + 7 * Math.sqrt(b.count / cmax)).toFixed(1), "data-lo": b.lo, "data-count": b.count },
          s("title", null, `${fmt(b.lo, 1)}–${fmt(b.hi, 1)}: mean q ${fmt(b.mean_q, 3)}, frequency ${fmt(b.freq, 3)}, ${b.count} pairs`)));
      }
      if (!bins.length) svg.append(s("text", { class: "tick", x: xs(0.5), y: ys(0.55), "text-anchor": "middle" }, "no labelled pairs yet"));
      $("calibration-chart").replaceChildren(svg);
    }
    const labels = (sm.labels || []).map((l) => l.id);
    if (changed("serving", [sv, labels, st.threshold, st.thresholds, st.serving])) {
      setVal("serving-method", sv.method);
      setVal("serving-window", sv.window);
      const dec = Object.entries(sv.decisions || {});
      const total = dec.reduce((a, [, n]) => a + (isNum(n) ? n : 0), 0);
      const colour = (p, i) => PRED[p] || PALETTE[(i + 2) % PALETTE.length];
      $("serving-bar").replaceChildren(...dec.filter(([, n]) => n > 0).map(([p, n], i) =>
        h("span", { style: `width:${(100 * n) / total}%;background:${colour(p, i)}`, title: `${p}: ${n}` })));
      $("serving-decisions").tBodies[0].replaceChildren(...(dec.length ? dec.map(([p, n], i) => h("tr", { "data-predictor": p },
        h("td", null, swatch(colour(p, i)), p),
        h("td", { class: "num", "data-field": "count", "data-value": String(n) }, String(n)),
        h("td", { class: "num" }, total ? `${Math.round((100 * n) / total)}%` : "–"))) : [h("tr", null, h("td", { colspan: 3 }, none("no decisions yet")))]));
      // The switch's evidence (adaptive only): who serves, and the candidates' recent scores.
      const gate = (st.serving && st.serving.scores && st.serving.scores.length) ? st.serving.scores : null;
      const serving = st.serving ? st.serving.predictor : null;
      const short = { majority_vote: "vote", dawid_skene: "Dawid–Skene", model: "model", paper: "paper rule", model_paper_mean: "model + paper" };
      $("serving-gate").hidden = !gate;
      if (gate) {
        $("serving-gate").tBodies[0].replaceChildren(...gate.map((sc) => {
          const p = sc.predictor;
          return h("tr", { "data-predictor": p, class: p === serving ? "serving" : null },
            h("td", null, short[p] || p, p === serving ? " ✓" : ""),
            h("td", { class: "num", "data-field": "loss", "data-value": String(sc.loss) }, fmt(sc.loss, 1)),
            h("td", { class: "num", "data-field": "errors", "data-value": String(sc.errors) }, fmt(sc.errors, 1)),
            h("td", { class: "num", "data-field": "micro_f1", "data-value": String(sc.micro_f1) }, fmt(sc.micro_f1, 3)));
        }));
      }
      const rule = st.serving && st.serving.rule;
      $("serving-rule").textContent = !gate
        ? (rule === "model" ? "The model always serves." : "The paper method always serves its model.")
        : rule === "vote-fallback"
          ? "The vote serves until the model has made fewer errors than it on the labelled rounds, with a micro-F1 no lower."
          : "The candidate with the lowest recent loss (false alarms + 1.5 × misses, older labelled rounds discounted) serves; it changes only when another leads by the margin. Dawid–Skene serves before any label.";
      const ag = sv.agreement || {};
      $("serving-agreement").replaceChildren(...Object.keys(ag).map((n) => h("span", { class: "key", "data-reporter": n, "data-field": "agreement", "data-value": String(ag[n]) },
        swatch(colorOf(n)), `${n} ${fmt(ag[n], 2)}`)));
      const served = sv.labels || {};
      const ids = labels.length ? labels : Object.keys(served);
      $("serving-labels").replaceChildren(...ids.map((id) => {
        const thr = st.thresholds && isNum(st.thresholds[id]) ? st.thresholds[id] : st.threshold;
        const p = served[id];
        return h("li", { "data-label": id }, h("span", { class: "lab", title: labelName(id) }, id),
          h("b", { "data-field": "predictor", "data-value": p === undefined ? "null" : String(p), style: PRED[p] ? `color:${PRED[p]}` : null }, p || "–"),
          h("span", { class: "num", "data-field": "threshold", "data-value": String(thr), title: "threshold" }, fmt(thr, 2)));
      }));
    }
    setReady("panel-calibration");
  }

  // ---- panel 5: health ----
  function renderHealth(sm) {
    const he = sm.health;
    if (!he || !changed("health", he)) return;
    setVal("health-ready", he.ready, he.ready ? "ready" : "not ready");
    $("health-ready").className = he.ready ? "status ok" : "status bad";
    $("health-not-ready").replaceChildren(...(he.not_ready || []).map((r) => h("li", null, r)));
    setVal("queue-depth", he.queue_depth);
    const er = he.errors || {};
    for (const k of ["client", "server", "overload"]) setVal(`errors-${k}`, er[k]);
    setVal("health-labeler", he.labeler);
    setVal("health-embedder", he.embedder, he.embedder == null ? "none" : String(he.embedder));
    const cell = (name, field, v, text, cls) => h("td", { class: cls || "num", "data-reporter": name, "data-field": field, "data-value": v === undefined ? "null" : String(v) }, text);
    $("health-reporters").tBodies[0].replaceChildren(...(he.reporters || []).map((r) => {
      const l = r.latency_ms || {};
      return h("tr", { class: r.ready || r.configured === false ? null : "not-ready" },
        h("th", { scope: "row" }, swatch(colorOf(r.name)), r.name),
        r.configured === false
          // Named in `reporters` but without a [[reporter]] section: it reports through /v1/fuse only.
          ? cell(r.name, "ready", "fuse-only", [h("span", { class: "dot", "aria-hidden": "true" }), "reports via /v1/fuse"], "ready-cell")
          : cell(r.name, "ready", !!r.ready, [h("span", { class: r.ready ? "dot ok" : "dot bad", "aria-hidden": "true" }), r.ready ? "ready" : "not ready"], "ready-cell"),
        cell(r.name, "p50", l.p50, fmtMs(l.p50)),
        cell(r.name, "p95", l.p95, fmtMs(l.p95)),
        cell(r.name, "p99", l.p99, fmtMs(l.p99)),
        cell(r.name, "count", l.count, isNum(l.count) ? String(l.count) : "–"),
        cell(r.name, "failures", r.failures, isNum(r.failures) ? String(r.failures) : "–", r.failures > 0 ? "num bad" : "num"),
        h("td", { class: "detail" }, r.detail == null ? "" : String(r.detail)));
    }));
    setReady("panel-health");
  }

  function renderSummary(sm) {
    summary = sm;
    renderHeader(sm);
    renderReputations(sm);
    renderReliability(sm);
    renderCalibration(sm);
    renderHealth(sm);
    if (rp.data) renderRounds();
    if (rv.data) renderRound();
  }
  async function loadSummary() {
    renderSummary(await api("/ui/api/summary"));
  }

  // ---- panel 4: rounds ----
  const rp = { before: null, stack: [], data: null, req: 0 };
  const newerBtn = $("rounds-newer"), olderBtn = $("rounds-older");
  async function loadRounds() {
    const before = rp.before;
    const req = ++rp.req;
    const d = await api(`/ui/api/rounds?limit=${PAGE}` + (before === null ? "" : `&before=${encodeURIComponent(before)}`));
    if (req !== rp.req || before !== rp.before) return;
    rp.data = d;
    renderRounds();
  }
  function goPage() {
    newerBtn.disabled = olderBtn.disabled = true;
    loadRounds().then(() => clearBanner(), (e) => { showBanner(e.message, "fetch"); renderRounds(); });
  }
  olderBtn.addEventListener("click", () => {
    if (!rp.data || rp.data.next_before === null || rp.data.next_before === undefined) return;
    rp.stack.push(rp.before);
    rp.before = rp.data.next_before;
    goPage();
  });
  newerBtn.addEventListener("click", () => {
    if (!rp.stack.length) return;
    rp.before = rp.stack.pop();
    goPage();
  });
  function renderRounds() {
    const d = rp.data;
    const rounds = d.rounds || [];
    let reps = reportersOf(summary);
    if (!reps.length) reps = [...new Set(rounds.flatMap((r) => Object.keys(r.reporters || {})))];
    newerBtn.disabled = rp.before === null;
    olderBtn.disabled = d.next_before === null || d.next_before === undefined;
    if (!changed("rounds", [reps, d, rp.before, summary && summary.labels])) return;
    const page = rp.stack.length + 1;
    $("rounds-page").textContent = rounds.length
      ? `page ${page} · ${rounds[0].round_id} … ${rounds[rounds.length - 1].round_id} · ${d.total} stored` + (page === 1 ? " · live" : "")
      : `page ${page} · ${d.total} stored`;
    $("rounds-head").replaceChildren(...["round", "time", "clip", "fused labels"].map((t) => h("th", null, t)),
      ...reps.map((n) => h("th", { "data-reporter": n }, swatch(colorOf(n)), n)),
      ...["failures", "labelled", "decision"].map((t) => h("th", null, t)));
    const rows = rounds.map((r) => {
      const failed = r.failed || {};
      const fails = Object.entries(failed);
      return h("tr", { "data-round-id": r.round_id, class: fails.length ? "has-failures" : null },
        h("td", null, h("a", { href: `#/rounds/${encodeURIComponent(r.round_id)}` }, r.round_id)),
        h("td", { class: "nowrap", "data-value": r.created_ms }, fmtTime(r.created_ms)),
        h("td", { class: "clip", title: r.clip == null ? null : String(r.clip) }, r.clip == null ? none() : String(r.clip)),
        h("td", { "data-field": "labels" }, r.labels && r.labels.length ? chips(r.labels) : none("none")),
        reps.map((n) => h("td", { "data-reporter": n, "data-field": "labels" },
          failed[n] !== undefined ? h("span", { class: "fail", title: String(failed[n]) }, "failed")
            : r.reporters && r.reporters[n] ? (r.reporters[n].length ? chips(r.reporters[n]) : none("none")) : none())),
        h("td", { class: "failures", "data-field": "failed", "data-value": String(fails.length) },
          fails.map(([n, msg]) => h("div", { class: "fail" }, `${n}: ${msg}`))),
        h("td", { class: "center", "data-field": "labelled", "data-value": String(!!r.labelled) },
          r.labelled ? h("span", { class: "check", title: "labelled", "aria-label": "labelled" }, "✓") : ""),
        h("td", { "data-field": "decision" }, r.decision == null ? none() : String(r.decision)));
    });
    $("rounds-body").replaceChildren(...(rows.length ? rows : [h("tr", null, h("td", { colspan: reps.length + 7 }, none("No rounds stored yet.")))]));
    setReady("panel-rounds");
  }

  // ---- panel: the review queue (GET /v1/review; docs/METHOD.md §7) ----
  // The queue costs window² cosines, so it is fetched at start, on Refresh and at most every
  // REVIEW_MS while the dashboard polls, not on every tick.
  const REVIEW_MS = 30000;
  const rq = { data: null, req: 0, at: 0 };
  async function loadReview() {
    const req = ++rq.req;
    rq.at = Date.now();
    const d = await api("/v1/review?limit=10&window=500");
    if (req !== rq.req) return;
    rq.data = d;
    renderReview();
  }
  function renderReview() {
    const d = rq.data;
    if (!d || !changed("review", d)) return;
    $("review-note").textContent = `${d.candidates} of the latest ${d.considered} rounds not fully labelled · ${d.labelled} labelled · built ${fmtTime(rq.at)}`;
    const rows = (d.queue || []).map((p, i) => h("tr", { "data-round-id": p.round_id },
      h("td", { class: "num" }, String(i + 1)),
      h("td", null, h("a", { href: `#/rounds/${encodeURIComponent(p.round_id)}` }, p.round_id)),
      h("td", { class: "num", "data-value": String(p.represents) }, String(p.represents)),
      h("td", { class: "num", "data-value": String(p.novelty) }, p.novelty.toFixed(2)),
      h("td", { "data-field": "disputed" }, p.disputed.length ? chips(p.disputed) : none("none")),
      h("td", null, p.reasons.join("; "))));
    $("review-body").replaceChildren(...(rows.length ? rows
      : [h("tr", null, h("td", { colspan: 6 }, none("Nothing to label: every stored round of the window is labelled.")))]));
    setReady("panel-review");
  }
  $("review-refresh").addEventListener("click", () => {
    loadReview().then(() => clearBanner(), (e) => showBanner(e.message, "fetch"));
  });

  // ---- round page ----
  const rv = { id: null, data: null, req: 0, touched: new Set(), formKey: null, sending: false };
  const panelRound = $("panel-round");
  async function loadRound(id) {
    const req = ++rv.req;
    let d;
    try {
      d = await api(`/ui/api/rounds/${encodeURIComponent(id)}`);
    } catch (e) {
      if (rv.id === id && req === rv.req && e.status === 404) { roundMissing(id, e.message); return; }
      throw e;
    }
    if (rv.id !== id || req !== rv.req) return;
    rv.data = d;
    renderRound();
  }
  function roundMissing(id, msg) {
    rv.data = null;
    rv.formKey = null;
    memo.round = null;
    delete panelRound.dataset.ready;
    panelRound.dataset.error = "not_found";
    $("round-body").replaceChildren(h("p", { class: "error" }, `Round ${id} not found: ${msg}`));
  }
  function roundSkeleton() {
    const body = $("round-body");
    if ($("round-facts")) return;
    const result = h("div", { id: "feedback-result", "aria-live": "polite" });
    result.hidden = true;
    const form = h("form", { id: "feedback-form" },
      h("fieldset", null, h("legend", null, "Labels present in this clip"),
        h("p", { class: "note" }, "Checked means present, unchecked means absent: every label is sent as known. Boxes start at the known truth, else at the fused labels."),
        h("div", { class: "checks", id: "feedback-checks" })),
      h("div", { class: "controls" },
        h("button", { id: "send-feedback", type: "submit", class: "primary" }, "Send feedback"),
        h("button", { id: "feedback-reset", type: "button" }, "Reset boxes")),
      result);
    form.addEventListener("submit", sendFeedback);
    form.addEventListener("change", (e) => {
      const cb = e.target;
      if (cb.name !== "label") return;
      rv.touched.add(cb.value);
      cb.parentElement.classList.toggle("changed", cb.checked !== (cb.dataset.default === "true"));
    });
    form.querySelector("#feedback-reset").addEventListener("click", () => {
      for (const cb of form.querySelectorAll('input[name="label"]')) cb.checked = cb.dataset.default === "true";
      rv.touched.clear();
      if (rv.data) applyDefaults(rv.data);
    });
    body.replaceChildren(
      h("dl", { class: "facts-grid", id: "round-facts" }),
      h("h3", null, "Fused labels"), h("div", { id: "round-labels" }),
      h("h3", null, "Failures"), h("ul", { id: "round-failures", class: "bad-list" }),
      h("h3", null, "Labels: posterior, truth and explanation"),
      h("div", { class: "scroll" }, h("table", { id: "round-posteriors" })),
      h("h3", null, "Reporters"), h("div", { id: "round-reporters", class: "cards" }),
      h("h3", null, "Frames"), h("div", { id: "round-frames", class: "frames" }),
      h("h3", null, "Feedback"), h("div", { id: "round-feedback-history" }),
      form);
  }
  const truthOf = (d, id) => (d.truth ? d.truth[id] : null);
  const defaultOf = (d, id) => {
    const t = truthOf(d, id);
    return t === true || t === false ? t : (d.labels || []).includes(id);
  };
  const labelIdsOf = (d) => (summary && summary.labels && summary.labels.length ? summary.labels.map((l) => l.id) : Object.keys(d.posteriors || {}));
  function applyDefaults(d) {
    for (const cb of $("feedback-checks").querySelectorAll('input[name="label"]')) {
      // A box that differs from what the page last set was changed by the operator (also when
      // set from a script, which fires no change event): keep it.
      if (cb.dataset.default !== undefined && String(cb.checked) !== cb.dataset.default) rv.touched.add(cb.value);
      const def = defaultOf(d, cb.value);
      cb.dataset.default = String(def);
      if (!rv.touched.has(cb.value)) cb.checked = def;
      cb.parentElement.classList.toggle("changed", cb.checked !== def);
    }
  }
  function renderForm(d) {
    const ids = labelIdsOf(d);
    const key = ids.join("\n");
    if (rv.formKey !== key) {
      const prev = new Map([...$("feedback-checks").querySelectorAll('input[name="label"]')].map((c) => [c.value, c.checked]));
      $("feedback-checks").replaceChildren(...ids.map((id) => {
        const cb = h("input", { type: "checkbox", name: "label", value: id });
        if (rv.touched.has(id) && prev.has(id)) cb.checked = prev.get(id);
        return h("label", { class: "check-item", title: labelName(id) }, cb, h("span", null, id));
      }));
      rv.formKey = key;
    }
    applyDefaults(d);
  }
  function renderRound() {
    const d = rv.data;
    if (!d) return;
    roundSkeleton();
    delete panelRound.dataset.error;
    renderForm(d);
    const labels = labelIdsOf(d);
    if (!changed("round", [d, labels, reportersOf(summary)])) { panelRound.dataset.ready = "true"; return; }
    const reps = [...new Set([...Object.keys(d.reporters || {}), ...Object.keys(d.failed || {})])];
    const fused = new Set(d.labels || []);
    const thrOf = (id) => (d.thresholds && isNum(d.thresholds[id]) ? d.thresholds[id] : d.threshold);
    $("round-title").textContent = `Round ${d.round_id}`;
    const fact = (k, id, v, text) => [h("dt", null, k), h("dd", { id, "data-value": v === undefined ? "null" : String(v) }, text !== undefined ? text : v == null ? "–" : String(v))];
    $("round-facts").replaceChildren(
      ...fact("clip", "round-clip", d.clip),
      ...fact("time", "round-time", d.created_ms, fmtTime(d.created_ms)),
      ...fact("seq", "round-seq", d.seq),
      ...fact("method", "round-method", d.method),
      ...fact("decision", "round-decision", d.decision),
      ...fact("threshold", "round-threshold", d.threshold, fmt(d.threshold, 2) + (d.thresholds ? " (per-label thresholds below)" : "")),
      ...fact("coalition", "round-coalition", (d.coalition || []).join(","), (d.coalition || []).join(", ") || "none"),
      ...fact("missing", "round-missing", (d.missing || []).join(","), (d.missing || []).join(", ") || "none"));
    $("round-labels").replaceChildren(fused.size ? chips(d.labels) : none("no label above its threshold"));
    const fails = Object.entries(d.failed || {});
    $("round-failures").replaceChildren(...(fails.length ? fails.map(([n, m]) => h("li", { "data-reporter": n }, h("b", null, n), `: ${m}`)) : [h("li", { class: "none" }, "none")]));
    // labels table
    const ex = d.explanation || {};
    let cmax = 0;
    for (const id of labels) for (const v of Object.values((ex[id] && ex[id].contributions) || {})) if (isNum(v)) cmax = Math.max(cmax, Math.abs(v));
    const bar = (v, thr) => h("span", { class: "pbar" }, h("i", { style: `width:${(Math.min(1, Math.max(0, v)) * 100).toFixed(1)}%` }),
      isNum(thr) ? h("b", { style: `left:${(Math.min(1, Math.max(0, thr)) * 100).toFixed(1)}%`, title: `threshold ${thr}` }) : null);
    const div = (v) => {
      const w = cmax ? (Math.abs(v) / cmax) * 50 : 0;
      return h("span", { class: "dbar" }, h("i", { class: v >= 0 ? "pos" : "neg", style: v >= 0 ? `left:50%;width:${w.toFixed(1)}%` : `left:${(50 - w).toFixed(1)}%;width:${w.toFixed(1)}%` }));
    };
    const yn = (b) => (b ? "yes" : "no");
    const head = h("tr", null, ["label", "posterior", "threshold", "fused", "truth", "prior"].map((t) => h("th", null, t)),
      reps.map((n) => h("th", { "data-reporter": n, title: "contribution to the logit (weighted log-likelihood ratio)" }, swatch(colorOf(n)), n)), h("th", null, "logit"));
    const rows = labels.map((id) => {
      const p = d.posteriors ? d.posteriors[id] : undefined;
      const t = truthOf(d, id);
      const e = ex[id] || {};
      const src = d.truth_source && d.truth_source[id];
      const known = t === true || t === false;
      return h("tr", { "data-label": id, class: [fused.has(id) ? "fused" : "", known && t !== fused.has(id) ? "mismatch" : ""].join(" ").trim() || null },
        h("th", { scope: "row", title: labelName(id) }, id),
        h("td", { class: "num", "data-field": "posterior", "data-value": p === undefined ? "null" : String(p) }, isNum(p) ? bar(p, thrOf(id)) : null, fmt(p, 3)),
        h("td", { class: "num", "data-field": "threshold", "data-value": String(thrOf(id)) }, fmt(thrOf(id), 2)),
        h("td", { "data-field": "fused", "data-value": String(fused.has(id)) }, yn(fused.has(id))),
        h("td", { "data-field": "truth", "data-value": known ? String(t) : "null" }, known ? yn(t) : none("unknown"), src ? h("small", { class: "src" }, ` (${src})`) : null),
        h("td", { class: "num", "data-field": "prior", "data-value": e.prior === undefined ? "null" : String(e.prior) }, fmt(e.prior, 2)),
        reps.map((n) => {
          const v = e.contributions ? e.contributions[n] : undefined;
          return h("td", { class: "num contrib", "data-reporter": n, "data-field": "contribution", "data-value": v === undefined ? "null" : String(v) }, isNum(v) ? [div(v), fmt(v, 2)] : none());
        }),
        h("td", { class: "num", "data-field": "logit", "data-value": e.logit === undefined ? "null" : String(e.logit) }, fmt(e.logit, 2)));
    });
    $("round-posteriors").replaceChildren(h("thead", null, head), h("tbody", null, rows));
    // reporters
    $("round-reporters").replaceChildren(...reps.map((n) => {
      const r = (d.reporters || {})[n] || {};
      const f = (d.failed || {})[n];
      const inC = (d.coalition || []).includes(n);
      return h("div", { class: "card", "data-reporter": n },
        h("h4", null, swatch(colorOf(n)), n, h("span", { class: inC ? "tag" : "tag off" }, inC ? "in coalition" : "missing")),
        f !== undefined ? h("p", { class: "fail" }, `failed: ${f}`) : null,
        h("div", { "data-field": "labels" }, r.labels && r.labels.length ? chips(r.labels) : none("no labels")),
        r.text == null ? h("p", { class: "muted", "data-field": "text" }, "no text (labels were sent directly)")
          : h("pre", { class: "report-text", "data-field": "text" }, String(r.text)));
    }));
    // frames (rebuilt only when they change, so images do not flicker)
    const frames = d.frames || [];
    if (changed("frames", [d.round_id, frames])) {
      $("round-frames").replaceChildren(...(frames.length ? frames.map((f) => {
        const img = h("img", { class: "frame", src: f.url, alt: `frame ${f.index} at ${f.t_s} s`, loading: "lazy", "data-index": f.index });
        const fig = h("figure", null, img, h("figcaption", null, `t = ${fmt(f.t_s, 1)} s`));
        img.addEventListener("error", () => { img.classList.add("broken"); fig.insertBefore(h("span", { class: "noimg" }, "frame unavailable"), fig.lastChild); }, { once: true });
        return fig;
      }) : [h("p", { class: "empty", id: "no-frames" }, "no frames stored")]));
    }
    // earlier feedback
    const fb = d.feedback || [];
    $("round-feedback-history").replaceChildren(fb.length ? h("table", { id: "round-feedback" },
      h("thead", null, h("tr", null, ["time", "source", "labels present", "labels known"].map((t) => h("th", null, t)))),
      h("tbody", null, fb.map((f) => h("tr", { "data-source": f.source },
        h("td", { class: "nowrap" }, fmtTime(f.created_ms)), h("td", null, f.source),
        h("td", null, f.labels && f.labels.length ? chips(f.labels) : none("none")),
        h("td", { class: "num" }, `${(f.known || []).length} of ${labels.length}`))))) : h("p", { class: "empty", id: "no-feedback" }, "no feedback yet"));
    panelRound.dataset.ready = "true";
  }
  async function sendFeedback(ev) {
    ev.preventDefault();
    if (rv.sending || !rv.id) return;
    const id = rv.id;
    const form = $("feedback-form");
    const labels = [...form.querySelectorAll('input[name="label"]:checked')].map((c) => c.value);
    const btn = $("send-feedback");
    const out = $("feedback-result");
    rv.sending = true;
    btn.disabled = true;
    out.hidden = false;
    delete out.dataset.status; // data-status appears only with the answer: ok or error
    out.classList.add("pending");
    out.textContent = "sending…";
    try {
      const r = await api("/v1/feedback", {
        method: "POST",
        headers: { "Content-Type": "application/json", Accept: "application/json", "X-Vlmfuse-Ui": "1" },
        body: JSON.stringify({ round_id: id, labels }),
      });
      const parts = [];
      if (r.learned && typeof r.learned === "object") {
        const n = Array.isArray(r.learned) ? r.learned.length : Object.keys(r.learned).length;
        parts.push(`learned ${n} label${n === 1 ? "" : "s"}`);
      } else parts.push("feedback stored");
      if (r.reputations) parts.push("reputations now " + Object.entries(r.reputations).map(([k, v]) => `${k}=${fmt(v, 2)}`).join(", "));
      if (Array.isArray(r.ignored) && r.ignored.length) parts.push("not taken: " + r.ignored.map((i) => (i.reason ? `${i.label} (${i.reason})` : i.label)).join(", "));
      if (rv.id === id) {
        out.dataset.status = "ok";
        out.textContent = parts.join("; ");
        // What was sent is the truth now: the boxes are no longer the operator's changes.
        for (const cb of form.querySelectorAll('input[name="label"]')) cb.dataset.default = String(cb.checked);
        rv.touched.clear();
      }
      memo.rounds = null;
      rq.at = 0; // the queue is rebuilt at the dashboard's next tick: this round may leave it
      const res = await Promise.allSettled([loadRound(id), loadSummary()]);
      const bad = res.find((x) => x.status === "rejected");
      if (bad) showBanner(bad.reason.message, "fetch");
    } catch (e) {
      if (e.status !== 401 && rv.id === id) {
        out.dataset.status = "error";
        out.textContent = e.message;
      }
    } finally {
      out.classList.remove("pending");
      rv.sending = false;
      btn.disabled = false;
    }
  }

  // ---- routing ----
  let dashScroll = 0;
  function route() {
    const m = location.hash.match(/^#\/rounds\/([^/?#]+)/);
    let id = null;
    if (m) { try { id = decodeURIComponent(m[1]); } catch (_) { id = m[1]; } }
    if (id) {
      if (!rv.id) dashScroll = window.scrollY;
      if (rv.id !== id) {
        rv.id = id;
        rv.data = null;
        rv.touched.clear();
        rv.formKey = null;
        memo.round = memo.frames = null;
        panelRound.dataset.roundId = id;
        delete panelRound.dataset.ready;
        delete panelRound.dataset.error;
        $("round-title").textContent = `Round ${id}`;
        $("round-body").replaceChildren(h("p", { class: "empty" }, "loading…"));
        window.scrollTo(0, 0);
      }
      $("dashboard").hidden = true;
      $("round-view").hidden = false;
      document.title = `${id} · vlmfuse`;
    } else {
      const wasRound = rv.id !== null;
      rv.id = null;
      rv.data = null;
      $("round-view").hidden = true;
      $("dashboard").hidden = false;
      document.title = "vlmfuse";
      if (wasRound) window.scrollTo(0, dashScroll);
    }
    tick();
  }
  window.addEventListener("hashchange", route);

  // ---- polling ----
  let timer = null, inflight = false, again = false;
  function schedule() {
    clearTimeout(timer);
    timer = null;
    if (document.visibilityState === "hidden") { setLive("paused", "paused (tab hidden)"); return; }
    timer = setTimeout(tick, POLL_MS);
  }
  async function tick() {
    if (inflight) { again = true; return; }
    if (document.visibilityState === "hidden") { schedule(); return; }
    clearTimeout(timer);
    inflight = true;
    try {
      const jobs = [loadSummary()];
      if (rv.id) jobs.push(loadRound(rv.id));
      else if (rp.before === null) jobs.push(loadRounds());
      if (!rv.id && Date.now() - rq.at > REVIEW_MS) jobs.push(loadReview());
      const res = await Promise.allSettled(jobs);
      const bad = res.find((r) => r.status === "rejected");
      if (reloading) return;
      if (bad) {
        showBanner(`${bad.reason.message} — retrying every ${POLL_MS / 1000} s`, "fetch");
        setLive("error", "error, retrying");
      } else {
        clearBanner();
        setLive("live", `live · ${POLL_MS / 1000} s`);
      }
    } finally {
      inflight = false;
      if (again) { again = false; tick(); } else if (!reloading) schedule();
    }
  }
  document.addEventListener("visibilitychange", () => {
    if (document.visibilityState === "hidden") { clearTimeout(timer); timer = null; setLive("paused", "paused (tab hidden)"); }
    else tick();
  });

  // ---- keyboard ----
  document.addEventListener("keydown", (e) => {
    if (e.ctrlKey || e.metaKey || e.altKey) return;
    const t = e.target;
    const typing = t && (t.isContentEditable || /^(INPUT|TEXTAREA|SELECT)$/.test(t.tagName));
    if (e.key === "Escape" && rv.id) { location.hash = "#/"; return; }
    if (typing) return;
    if (e.key === "[" && !rv.id) newerBtn.click();
    else if (e.key === "]" && !rv.id) olderBtn.click();
    else if (e.key === ".") tick();
  });

  if (sessionStorage.getItem("vlmfuse-401") && Date.now() - Number(sessionStorage.getItem("vlmfuse-401")) > 10000) sessionStorage.removeItem("vlmfuse-401");
  route();
})();
