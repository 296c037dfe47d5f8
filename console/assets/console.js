// Paddock console: the create-model wizard and a model's live page. The graphs are uPlot's,
// the editor CodeMirror's, the buttons htmx's; this file only wires them to the API.
"use strict";
var Paddock = (function () {
  function $(sel, root) { return (root || document).querySelector(sel); }
  function $$(sel, root) { return Array.prototype.slice.call((root || document).querySelectorAll(sel)); }
  function val(name) {
    var el = $('[name="' + name + '"]:checked') || $('[name="' + name + '"]');
    return el ? el.value : null;
  }
  function num(name) { return Number(val(name)); }
  function text(el, s) { el.textContent = s; return el; }
  function li(s) { return text(document.createElement("li"), s); }

  // ---- The wizard ----------------------------------------------------------------------
  function wizard() {
    var step = 1, last = 5;
    var editor = CodeMirror.fromTextArea($("#reward"), {
      mode: "python", lineNumbers: true, indentUnit: 4, gutters: ["CodeMirror-linenumbers", "marks"],
    });
    editor.setSize(null, 420);
    var marked = [];
    function clearMarks() {
      marked.forEach(function (n) { editor.removeLineClass(n, "background", "error-line"); });
      marked = [];
      editor.clearGutter("marks");
    }
    function markLine(line, message) {
      var n = line - 1;
      if (n < 0 || n >= editor.lineCount()) return;
      editor.addLineClass(n, "background", "error-line");
      var m = document.createElement("span");
      m.className = "error-mark";
      m.title = message;
      m.textContent = "●";
      editor.setGutterMarker(n, "marks", m);
      marked.push(n);
    }
    function show(n) {
      step = n;
      $$("section[data-step]").forEach(function (s) { s.hidden = Number(s.dataset.step) !== n; });
      $$(".steps li").forEach(function (s) { s.classList.toggle("current", Number(s.dataset.step) === n); });
      $("#back").disabled = n === 1;
      $("#next").hidden = n === last;
      $("#submit").hidden = n !== last;
      if (n === 5) editor.refresh();
    }
    $("#back").onclick = function () { show(Math.max(1, step - 1)); };
    $("#next").onclick = function () { show(Math.min(last, step + 1)); };
    $$(".steps li").forEach(function (s) { s.onclick = function () { show(Number(s.dataset.step)); }; });

    function raceChanged() {
      var t = val("race_type");
      $("#objects").hidden = t !== "object_avoidance";
      $("#bots").hidden = t !== "head_to_bot";
    }
    $$('[name="race_type"]').forEach(function (r) { r.onchange = raceChanged; });
    function algorithmChanged() {
      var sac = val("training_algorithm") === "sac";
      $$(".ppo").forEach(function (e) { e.hidden = sac; });
      $$(".sac").forEach(function (e) { e.hidden = !sac; });
      if (sac) $('[name="action_type"][value="continuous"]').checked = true;
      actionChanged();
    }
    $$('[name="training_algorithm"]').forEach(function (r) { r.onchange = algorithmChanged; });

    var lineActions = null;
    function discreteActions() {
      if (lineActions) return lineActions;
      var n = num("steer_n"), max = num("steer_max"), k = num("speed_n"), vmax = num("speed_max"), out = [];
      for (var i = 0; i < n; i++) {
        var steer = n === 1 ? 0 : -max + (2 * max * i) / (n - 1);
        for (var j = 1; j <= k; j++) out.push({ steering_angle: Math.round(steer * 100) / 100, speed: Math.round((vmax * j / k) * 100) / 100 });
      }
      return out;
    }
    function actionSpace() {
      if (val("action_type") === "discrete") return discreteActions();
      return { steering_angle: { low: num("steer_low"), high: num("steer_high") }, speed: { low: num("speed_low"), high: num("speed_high") } };
    }
    function drawActions() {
      var g = $("#action-graph"), space = actionSpace(), ns = "http://www.w3.org/2000/svg";
      while (g.firstChild) g.removeChild(g.firstChild);
      function at(steer, speed) {
        var a = (steer * Math.PI) / 180, r = (speed / 4) * 100;
        return [-Math.sin(a) * r, -Math.cos(a) * r];
      }
      function el(tag, attrs) {
        var e = document.createElementNS(ns, tag);
        Object.keys(attrs).forEach(function (k) { e.setAttribute(k, attrs[k]); });
        g.appendChild(e);
        return e;
      }
      el("path", { d: "M-100,0 A100,100 0 0 1 100,0", fill: "none", stroke: "#ccc" });
      if (Array.isArray(space)) {
        var rows = $("#action-rows");
        while (rows.firstChild) rows.removeChild(rows.firstChild);
        space.forEach(function (a, i) {
          var p = at(a.steering_angle, a.speed);
          el("line", { x1: 0, y1: 0, x2: p[0], y2: p[1], stroke: "#1f77b4" });
          el("circle", { cx: p[0], cy: p[1], r: 3, fill: "#1f77b4" });
          var tr = document.createElement("tr");
          [i, a.steering_angle, a.speed].forEach(function (v) { tr.appendChild(text(document.createElement("td"), String(v))); });
          rows.appendChild(tr);
        });
      } else {
        var lo = at(space.steering_angle.high, space.speed.high), hi = at(space.steering_angle.low, space.speed.high);
        var lo2 = at(space.steering_angle.high, space.speed.low), hi2 = at(space.steering_angle.low, space.speed.low);
        el("path", {
          d: "M" + lo2 + " L" + lo + " A" + (space.speed.high / 4) * 100 + "," + (space.speed.high / 4) * 100 + " 0 0 1 " + hi +
             " L" + hi2 + " A" + (space.speed.low / 4) * 100 + "," + (space.speed.low / 4) * 100 + " 0 0 0 " + lo2 + "Z",
          fill: "rgba(31,119,180,0.3)", stroke: "#1f77b4",
        });
      }
    }
    function actionChanged() {
      var d = val("action_type") === "discrete";
      $("#discrete").hidden = !d;
      $("#continuous").hidden = d;
      drawActions();
    }
    $$('[name="action_type"]').forEach(function (r) { r.onchange = actionChanged; });
    function generatorChanged() { lineActions = null; text($("#actions-note"), ""); drawActions(); }
    $$("#continuous input, #discrete input, #discrete select").forEach(function (e) { e.oninput = generatorChanged; e.onchange = generatorChanged; });
    function firstTrack() { var c = $('[name="tracks"]:checked'); return c ? c.value : null; }
    function reversed() { return val("direction") === "reversed"; }
    // DRoA's names for the two ways round, from the first picked track's own.
    function directionChanged() {
      var c = $('[name="tracks"]:checked'), ccw = !c || c.dataset.forward !== "clockwise";
      text($("#dir-forward"), ccw ? "Counterclockwise" : "Clockwise");
      text($("#dir-reversed"), ccw ? "Clockwise" : "Counterclockwise");
      showRaceLine();
    }
    $$('[name="direction"]').forEach(function (r) { r.onchange = directionChanged; });
    $("#actions-from-line").onclick = function () {
      var t = firstTrack();
      if (!t) return;
      fetch("/api/v1/tracks/" + encodeURIComponent(t) + "/race_line?actions=" + (num("steer_n") * num("speed_n")) + "&reversed=" + reversed())
        .then(function (r) { return r.json(); }).then(function (v) {
          if (!v.actions) { text($("#actions-note"), v.error); return; }
          lineActions = v.actions;
          text($("#actions-note"), v.actions.length + " actions that drive " + t + "'s racing line");
          drawActions();
        });
    };
    var shownLine = null;
    function showRaceLine() {
      var t = firstTrack(), key = t + (reversed() ? " (reversed)" : "");
      $("#race-line-box").hidden = !t;
      if (!t || key === shownLine) return;
      shownLine = key;
      text($("#race-line-track"), key);
      fetch("/api/v1/tracks/" + encodeURIComponent(t) + "/race_line?reversed=" + reversed()).then(function (r) { return r.json(); }).then(function (v) {
        if (shownLine !== key) return;
        var box = $("#race-line");
        while (box.firstChild) box.removeChild(box.firstChild);
        if (!v.svg) { text($("#race-line-time"), v.error || ""); return; }
        var doc = new DOMParser().parseFromString(v.svg, "image/svg+xml");
        box.appendChild(document.importNode(doc.documentElement, true));
        text($("#race-line-time"), "(a lap in " + v.lap_time_s.toFixed(2) + " s)");
      });
    }
    $$('[name="tracks"]').forEach(function (c) { c.addEventListener("change", directionChanged); });

    $("#find-track").oninput = function () {
      var q = this.value.toLowerCase();
      $$(".track").forEach(function (t) { t.hidden = t.dataset.name.indexOf(q) < 0; });
    };
    var samples = JSON.parse($("#samples-json").textContent);
    $("#use-sample").onclick = function () { editor.setValue(samples[Number($("#samples").value)].code); clearMarks(); };

    function metadata() {
      var sensors = [val("camera")], state = sensors[0] === "STATE_VECTOR";
      if ($('[name="lidar"]').checked && !state) sensors.push("SECTOR_LIDAR");
      return {
        action_space: actionSpace(), sensor: sensors, neural_network: state ? "PADDOCK_MLP" : val("neural_network"),
        training_algorithm: val("training_algorithm"), action_space_type: val("action_type"), version: "5",
      };
    }
    function hyperparameters() {
      var h = { batch_size: num("batch_size"), lr: num("lr"), discount_factor: num("discount_factor"), loss_type: val("loss_type") };
      if (val("training_algorithm") === "sac") {
        h.sac_alpha = num("sac_alpha");
        h.num_episodes_between_training = 1;
      } else {
        h.num_epochs = num("num_epochs");
        h.beta_entropy = num("beta_entropy");
        h.num_episodes_between_training = num("num_episodes_between_training");
      }
      return h;
    }
    function race() {
      var t = val("race_type"), r = { race_type: t };
      if (t === "object_avoidance") {
        r.number_of_obstacles = num("number_of_obstacles");
        r.randomize_obstacle_locations = $('[name="randomize_obstacle_locations"]').checked;
      }
      if (t === "head_to_bot") {
        r.number_of_bot_cars = num("number_of_bot_cars");
        r.bot_car_speed = num("bot_car_speed");
      }
      return r;
    }
    function stop() {
      var kind = val("stop_kind"), s = { minutes: num("minutes") };
      if (kind === "verified") { s.target_laps = 3; s.target_evals = 2; s.verify_trials = 10; }
      if (kind === "steps") s.env_steps_budget = num("env_steps_budget");
      return s;
    }
    function body() {
      var b = {
        name: $("#name").value, description: $("#description").value,
        tracks: $$('[name="tracks"]:checked').map(function (c) { return c.value; }),
        reward_function: editor.getValue(), model_metadata: metadata(), hyperparameters: hyperparameters(),
        stop: stop(), race: race(), reversed: reversed(),
      };
      if ($('[name="agents"]').value) b.agents = num("agents");
      if (prefill && prefill.clone_from) b.clone_from = prefill.clone_from;
      return b;
    }

    function showValidation(v) {
      var out = $("#validation");
      while (out.firstChild) out.removeChild(out.firstChild);
      clearMarks();
      var head = document.createElement("p");
      head.className = v.ok ? "passed" : "failed";
      text(head, v.ok ? "Your reward function passed validation" + (v.warnings.length ? ", with " + v.warnings.length + " warning(s)." : ".")
                      : "Validation found " + v.errors.length + " error(s).");
      out.appendChild(head);
      var list = document.createElement("ul");
      v.errors.concat(v.warnings).forEach(function (f) {
        list.appendChild(li((f.line ? "line " + f.line + ": " : "") + f.message));
      });
      out.appendChild(list);
      v.errors.forEach(function (f) { if (f.line) markLine(f.line, f.message); });
    }
    $("#validate").onclick = function () {
      var button = this;
      button.disabled = true;
      text(button, "Validating…");
      fetch("/api/v1/rewards/validate", {
        method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ reward_function: editor.getValue(), track: $("#validate-track").value, reversed: reversed(), model_metadata: metadata() }),
      }).then(function (r) { return r.json(); }).then(function (v) {
        if (v.errors && v.ok === undefined) v = { ok: false, errors: v.errors, warnings: [] };
        showValidation(v);
      }).finally(function () { button.disabled = false; text(button, "Validate"); });
    };

    $("#dry-run").onclick = function () {
      var button = this;
      button.disabled = true;
      fetch("/api/v1/rewards/dry_run", {
        method: "POST", headers: { "Content-Type": "application/json" },
        body: JSON.stringify({ reward_function: editor.getValue(), track: $("#validate-track").value, reversed: reversed() }),
      }).then(function (r) { return r.json(); }).then(function (v) {
        if (!v.svg) { showValidation({ ok: false, errors: v.errors || [{ message: v.error }], warnings: [] }); return; }
        var box = $("#dry-run-lap");
        while (box.firstChild) box.removeChild(box.firstChild);
        var doc = new DOMParser().parseFromString(v.svg, "image/svg+xml");
        box.appendChild(document.importNode(doc.documentElement, true));
        text($("#dry-run-note"), "(" + v.track + ": " + v.status + " after " + v.steps + " steps, total reward " + v.total_reward.toFixed(1) + "; blue low, red high)");
        $("#dry-run-box").hidden = false;
      }).finally(function () { button.disabled = false; });
    };
    $("#wizard").onsubmit = function (ev) {
      ev.preventDefault();
      var errors = $("#errors");
      while (errors.firstChild) errors.removeChild(errors.firstChild);
      $("#submit").disabled = true;
      fetch("/api/v1/models", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body()) })
        .then(function (r) { return r.json().then(function (v) { return [r.status, v]; }); })
        .then(function (rv) {
          if (rv[0] === 201) { location.href = "/models/" + encodeURIComponent(rv[1].name); return; }
          var list = document.createElement("ul");
          (rv[1].errors || [{ field: "", message: rv[1].error }]).forEach(function (e) {
            list.appendChild(li((e.field ? e.field + ": " : "") + (e.line ? "line " + e.line + ": " : "") + e.message));
          });
          errors.appendChild(text(document.createElement("p"), "The model was not created:"));
          errors.appendChild(list);
          var reward = (rv[1].errors || []).filter(function (e) { return e.field === "reward_function"; });
          if (reward.length) { show(5); showValidation({ ok: false, errors: reward, warnings: [] }); }
        })
        .finally(function () { $("#submit").disabled = false; });
    };

    var prefill = JSON.parse($("#prefill").textContent);
    if (prefill) {
      $("#name").value = prefill.name || "";
      $("#description").value = prefill.description || "";
      if (prefill.reward_source) editor.setValue(prefill.reward_source);
      if (prefill.tracks) $$('[name="tracks"]').forEach(function (c) { c.checked = prefill.tracks.indexOf(c.value) >= 0; });
      var m = prefill.model_metadata || {};
      function set(name, v) { var e = $('[name="' + name + '"]'); if (e && v !== undefined && v !== null) e.value = v; }
      function pick(name, v) { var e = $('[name="' + name + '"][value="' + v + '"]'); if (e) e.checked = true; }
      pick("direction", prefill.reversed ? "reversed" : "forward");
      set("agents", prefill.agents);
      if (m.training_algorithm) pick("training_algorithm", m.training_algorithm);
      if (m.neural_network) set("neural_network", m.neural_network);
      if (Array.isArray(m.action_space)) {
        // A clone keeps the number of actions (DeepRacer's lock): its own list, to edit by generator or line.
        pick("action_type", "discrete");
        lineActions = m.action_space.map(function (a) { return { steering_angle: Number(a.steering_angle), speed: Number(a.speed) }; });
        text($("#actions-note"), lineActions.length + " actions of " + prefill.clone_from);
      } else if (m.action_space) {
        set("steer_low", m.action_space.steering_angle && m.action_space.steering_angle.low);
        set("steer_high", m.action_space.steering_angle && m.action_space.steering_angle.high);
        set("speed_low", m.action_space.speed && m.action_space.speed.low);
        set("speed_high", m.action_space.speed && m.action_space.speed.high);
      }
      var h = prefill.hyperparameters || {};
      if (h.batch_size) pick("batch_size", h.batch_size);
      if (h.loss_type) pick("loss_type", h.loss_type);
      ["num_epochs", "lr", "beta_entropy", "sac_alpha", "discount_factor", "num_episodes_between_training"].forEach(function (k) { set(k, h[k]); });
      var st = prefill.stop || {};
      if (st.minutes) set("minutes", st.minutes);
      if (st.env_steps_budget) { pick("stop_kind", "steps"); set("env_steps_budget", st.env_steps_budget); }
      else if (!st.target_laps) pick("stop_kind", "time");
      (m.sensor || []).forEach(function (s) {
        var c = $('[name="camera"][value="' + s + '"]');
        if (c) c.checked = true;
        if (s.indexOf("LIDAR") >= 0) $('[name="lidar"]').checked = true;
      });
      // DeepRacer's locks on a clone: the same algorithm, action-space type and sensors.
      $$('[name="training_algorithm"], [name="action_type"], [name="camera"], [name="lidar"]').forEach(function (e) { e.disabled = true; });
    }
    raceChanged();
    algorithmChanged();
    directionChanged();
    show(1);
  }

  // ---- A model's page ------------------------------------------------------------------
  function model() {
    var m = JSON.parse($("#model-json").textContent);
    var base = "/api/v1/models/" + encodeURIComponent(m.name);
    var data = { it: [], reward: [], progress: [], eval: [], evalReward: [], entropy: [], sps: [], world: {} };
    // A model of several worlds: each world's evaluation completion too.
    var worlds = m.tracks.length > 1 ? m.tracks : [];
    var palette = ["#2ca02c", "#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"];
    worlds.forEach(function (w) { data.world[w] = []; });
    var best = null;
    function bestMarker(u) {
      if (best === null) return;
      var x = u.valToPos(best, "x", true), ctx = u.ctx;
      ctx.save();
      ctx.strokeStyle = "#2ca02c";
      ctx.setLineDash([6, 4]);
      ctx.beginPath();
      ctx.moveTo(x, u.bbox.top);
      ctx.lineTo(x, u.bbox.top + u.bbox.height);
      ctx.stroke();
      ctx.restore();
    }
    var width = Math.min(640, $("#graph").clientWidth || 640);
    var graph = new uPlot({
      width: width, height: 300, hooks: { draw: [bestMarker] },
      scales: { x: { time: false } },
      axes: [{ label: "Iteration" }, { label: "Reward" }, { side: 1, scale: "%", label: "Completion (%)", grid: { show: false } }],
      series: [
        { label: "Iteration" },
        { label: "Average reward (training)", stroke: "#ff7f0e" },
        { label: "Average completion (training)", stroke: "#1f77b4", scale: "%" },
        { label: "Average completion (evaluation)", stroke: "#d62728", scale: "%", points: { show: true } },
        { label: "Average reward (evaluation)", stroke: "#e6550d", dash: [2, 3], points: { show: true } },
      ].concat(worlds.map(function (w, i) {
        return { label: "Evaluation: " + w, stroke: palette[i % palette.length], dash: [4, 4], scale: "%", points: { show: true } };
      })),
    }, [[], [], [], [], []].concat(worlds.map(function () { return []; })), $("#graph"));
    var second = new uPlot({
      width: width, height: 160, scales: { x: { time: false } },
      axes: [{ label: "Iteration" }, { label: "Entropy" }, { side: 1, scale: "sps", label: "Samples/s", grid: { show: false } }],
      series: [{ label: "Iteration" }, { label: "Entropy", stroke: "#9467bd" }, { label: "Samples/s (update)", stroke: "#8c564b", scale: "sps" }],
    }, [[], [], []], $("#entropy-graph"));
    // For the tests (and the curious, in the browser's console): the graphs.
    window.paddockGraphs = [graph, second];
    function redraw() {
      graph.setData([data.it, data.reward, data.progress, data.eval, data.evalReward].concat(worlds.map(function (w) { return data.world[w]; })));
      second.setData([data.it, data.entropy, data.sps]);
    }
    function addMetrics(v) {
      v.updates.forEach(function (u) {
        data.it.push(u.iteration); data.reward.push(u.reward); data.progress.push(u.progress);
        data.eval.push(null); data.evalReward.push(null); data.entropy.push(u.entropy === undefined ? null : u.entropy); data.sps.push(u.samples_per_s);
        worlds.forEach(function (w) { data.world[w].push(null); });
      });
      v.evaluations.forEach(function (e) {
        var i = data.it.lastIndexOf(e.iteration);
        if (i >= 0 && !e.verification) {
          data.eval[i] = e.progress;
          // Runs from before evaluations carried their reward have none to draw.
          data.evalReward[i] = e.reward === undefined ? null : e.reward;
          (e.worlds || []).forEach(function (w) { if (data.world[w[0]]) data.world[w[0]][i] = w[1]; });
        }
        if (e.best) best = e.iteration;
      });
      redraw();
    }
    var events = new EventSource(base + "/events");
    events.addEventListener("status", function (e) {
      var s = JSON.parse(e.data), el = $("#status");
      text(el, s.status);
      el.className = "status " + s.status;
      // A model waiting its turn says where it stands.
      text($("#queue-note"), s.job && s.job.queued ? "waiting its turn: " + s.job.queued + " in the queue" : "");
      $("#stop").disabled = s.status !== "training";
      $("#delete").disabled = s.status === "training" || s.status === "stopping";
      fetch(base).then(function (r) { return r.json(); }).then(function (v) {
        if (v.status_text) text($("#events"), v.status_text + (v.events && v.events.length ? "\n\n" + v.events.join("\n") : ""));
      });
    });
    events.addEventListener("metrics", function (e) { addMetrics(JSON.parse(e.data)); });
    events.addEventListener("camera", function (e) {
      var c = JSON.parse(e.data), box = $("#cameras");
      c.agents.forEach(function (a) {
        var fig = box.querySelector('[data-agent="' + CSS.escape(a.agent) + '"]');
        if (!fig) {
          fig = document.createElement("figure");
          fig.dataset.agent = a.agent;
          var img = document.createElement("img");
          img.width = 320;
          img.height = 240;
          img.alt = "The camera of " + a.agent;
          fig.appendChild(img);
          fig.appendChild(document.createElement("figcaption"));
          box.appendChild(fig);
        }
        if (fig.dataset.count !== String(a.count)) {
          fig.dataset.count = String(a.count);
          fig.querySelector("img").src = base + "/camera.png?agent=" + encodeURIComponent(a.agent) + "&n=" + a.count;
          text(fig.querySelector("figcaption"), a.agent + " on " + a.world + ", policy v" + a.policy_version);
        }
      });
      $("#camera-note").hidden = true;
    });
    // Evaluations: start one, list them, show one's trials, lap and frames.
    function cell(tr, s) { tr.appendChild(text(document.createElement("td"), s)); }
    function secs(s) {
      if (s === null || s === undefined) return "–";
      var m = Math.floor(s / 60), r = s - 60 * m;
      return (m < 10 ? "0" : "") + m + ":" + (r < 10 ? "0" : "") + r.toFixed(3);
    }
    function showEvaluation(id) {
      fetch(base + "/evaluations/" + encodeURIComponent(id)).then(function (r) { return r.json(); }).then(function (v) {
        $("#evaluation").hidden = false;
        text($("#evaluation-title"), v.name + " on " + v.track + (v.reversed ? " (reversed)" : "") + ", policy v" + v.policy_version);
        var rows = $("#trials tbody");
        while (rows.firstChild) rows.removeChild(rows.firstChild);
        (v.results || []).forEach(function (t) {
          var tr = document.createElement("tr");
          cell(tr, String(t.trial)); cell(tr, secs(t.time_s)); cell(tr, t.progress.toFixed(1) + " %"); cell(tr, t.status);
          cell(tr, String(t.resets)); cell(tr, String(t.off_tracks)); cell(tr, t.off_track_penalty_s ? t.off_track_penalty_s + " s" : "--");
          cell(tr, String(t.crashes)); cell(tr, t.crash_penalty_s ? t.crash_penalty_s + " s" : "--");
          rows.appendChild(tr);
        });
        $("#lap").src = base + "/evaluations/" + encodeURIComponent(id) + "/lap.svg";
        $("#frames").hidden = !v.frames;
        if (v.frames) $("#frames").src = base + "/evaluations/" + encodeURIComponent(id) + "/frames.png";
      });
    }
    function listEvaluations() {
      return fetch(base + "/evaluations").then(function (r) { return r.json(); }).then(function (list) {
        var rows = $("#evaluations tbody");
        while (rows.firstChild) rows.removeChild(rows.firstChild);
        list.forEach(function (e) {
          var tr = document.createElement("tr");
          cell(tr, e.name); cell(tr, new Date(e.created * 1000).toLocaleString()); cell(tr, e.status);
          cell(tr, secs(e.best_lap_s)); cell(tr, e.laps === undefined ? "–" : e.laps + "/" + e.trials); cell(tr, e.track); cell(tr, e.race_type);
          var td = document.createElement("td"), b = text(document.createElement("button"), "Show");
          b.type = "button";
          b.disabled = e.status !== "done";
          b.onclick = function () { showEvaluation(e.id); };
          td.appendChild(b);
          tr.appendChild(td);
          rows.appendChild(tr);
        });
        if (list.some(function (e) { return e.status === "running"; })) setTimeout(listEvaluations, 1000);
        else if (list.length && list[0].status === "done" && $("#evaluation").hidden) showEvaluation(list[0].id);
      });
    }
    $("#evaluate").onsubmit = function (ev) {
      ev.preventDefault();
      var race = val("eval_race"), n = num("eval_objects"), r = { race_type: race };
      if (race === "object_avoidance") { r.number_of_obstacles = n; r.randomize_obstacle_locations = true; }
      if (race === "head_to_bot") r.number_of_bot_cars = n;
      var body = { track: val("eval_track"), reversed: val("eval_reversed") === "true", trials: num("eval_trials"), race: r,
                   off_track_penalty: num("eval_off_track"), crash_penalty: num("eval_crash") };
      if ($('[name="eval_name"]').value) body.name = $('[name="eval_name"]').value;
      var box = $("#evaluation-error");
      box.hidden = true;
      fetch(base + "/evaluations", { method: "POST", headers: { "Content-Type": "application/json" }, body: JSON.stringify(body) })
        .then(function (r) { return r.json().then(function (v) { return [r.status, v]; }); })
        .then(function (rv) {
          if (rv[0] !== 202) { text(box, rv[1].error); box.hidden = false; return; }
          $("#evaluation").hidden = true;
          listEvaluations();
        });
    };
    listEvaluations();
    document.body.addEventListener("htmx:responseError", function (e) {
      var box = $("#action-error");
      try { text(box, JSON.parse(e.detail.xhr.responseText).error); } catch (_) { text(box, e.detail.xhr.statusText); }
      box.hidden = false;
    });
  }
  // ---- Import -------------------------------------------------------------------------
  function importer() {
    $("#archive").onchange = function () {
      var f = this.files[0];
      if (f && !$("#import-name").value) {
        $("#import-name").value = f.name.replace(/\.tar\.gz$|\.tgz$|\.tar$/, "").replace(/^physicalmodel-/, "").replace(/[^A-Za-z0-9-]/g, "-").slice(0, 64);
      }
    };
    $("#import").onsubmit = function (ev) {
      ev.preventDefault();
      var out = $("#import-errors"), f = $("#archive").files[0];
      while (out.firstChild) out.removeChild(out.firstChild);
      var q = "?name=" + encodeURIComponent($("#import-name").value) + "&description=" + encodeURIComponent($("#import-description").value);
      $("#import-submit").disabled = true;
      fetch("/api/v1/models/import" + q, { method: "POST", headers: { "Content-Type": "application/gzip" }, body: f || new Blob([]) })
        .then(function (r) { return r.json().then(function (v) { return [r.status, v]; }); })
        .then(function (rv) {
          if (rv[0] === 201) { location.href = "/models/" + encodeURIComponent(rv[1].name); return; }
          var list = document.createElement("ul");
          (rv[1].errors || [{ field: "", message: rv[1].error }]).forEach(function (e) { list.appendChild(li((e.field ? e.field + ": " : "") + e.message)); });
          out.appendChild(list);
        })
        .finally(function () { $("#import-submit").disabled = false; });
    };
  }
  // ---- Logins and users ----------------------------------------------------------------
  function showErrors(box, v) {
    while (box.firstChild) box.removeChild(box.firstChild);
    var list = document.createElement("ul");
    (v.errors || [{ message: v.error || "failed" }]).forEach(function (e) {
      list.appendChild(li((e.field ? e.field + ": " : "") + e.message));
    });
    box.appendChild(list);
  }
  function send(method, url, body) {
    return fetch(url, { method: method, headers: { "Content-Type": "application/json" }, body: body === undefined ? undefined : JSON.stringify(body) })
      .then(function (r) { return r.text().then(function (t) { return { ok: r.ok, v: t ? JSON.parse(t) : {} }; }); });
  }
  function login() {
    var next = JSON.parse($("#next-json").textContent);
    $("#login").onsubmit = function (ev) {
      ev.preventDefault();
      send("POST", "/api/v1/session", { user: $("#login-user").value, password: $("#login-password").value }).then(function (r) {
        if (r.ok) location.assign(next); else showErrors($("#login-errors"), r.v);
      });
    };
  }
  function invite() {
    var secret = JSON.parse($("#invitation-json").textContent);
    $("#invite").onsubmit = function (ev) {
      ev.preventDefault();
      if ($("#invite-password").value !== $("#invite-again").value) { showErrors($("#invite-errors"), { error: "the two passwords differ" }); return; }
      send("POST", "/api/v1/invitations", { invitation: secret, password: $("#invite-password").value }).then(function (r) {
        if (r.ok) location.assign("/login"); else showErrors($("#invite-errors"), r.v);
      });
    };
  }
  function users() {
    $$("#users tbody tr").forEach(function (tr) {
      var name = tr.dataset.user, url = "/api/v1/users/" + encodeURIComponent(name);
      function limit(sel) { var v = tr.querySelector(sel).value; return v === "" ? null : Number(v); }
      tr.querySelector(".user-save").onclick = function () {
        send("PATCH", url, { role: tr.querySelector(".user-role").value, quota: { models: limit(".user-models"), minutes: limit(".user-minutes") } })
          .then(function (r) { if (r.ok) location.reload(); else showErrors($("#users-errors"), r.v); });
      };
      tr.querySelector(".user-remove").onclick = function () {
        if (!confirm("Remove " + name + "? Their models stay.")) return;
        send("DELETE", url).then(function (r) { if (r.ok) location.reload(); else showErrors($("#users-errors"), r.v); });
      };
    });
    $("#add-user").onsubmit = function (ev) {
      ev.preventDefault();
      send("POST", "/api/v1/users", { name: $("#new-user").value, role: $("#new-role").value }).then(function (r) {
        if (!r.ok) { showErrors($("#users-errors"), r.v); return; }
        text($("#invitation-link"), location.origin + r.v.invitation);
        $("#invitation").hidden = false;
      });
    };
  }

  // ---- Races ---------------------------------------------------------------------------
  function races() {
    var form = $("#new-race");
    if (!form) return;
    var off = -new Date().getTimezoneOffset(), sign = off >= 0 ? "+" : "-";
    $$(".tz").forEach(function (el) {
      text(el, "your time (UTC" + sign + String(Math.floor(Math.abs(off) / 60)).padStart(2, "0") + ":" + String(Math.abs(off) % 60).padStart(2, "0") + ")");
    });
    function local(d) { return new Date(d.getTime() - d.getTimezoneOffset() * 60000).toISOString().slice(0, 16); }
    var now = new Date();
    $("#race-opens").value = local(now);
    $("#race-closes").value = local(new Date(now.getTime() + 7 * 86400000));
    function kind() {
      $("#race-objects-row").hidden = $("#race-type").value !== "object_avoidance";
      $("#race-bots-row").hidden = $("#race-type").value !== "head_to_bot";
    }
    $("#race-type").onchange = kind;
    function mode() {
      var live = val("race-mode") === "live";
      $("#race-opens-row").hidden = live;
      $("#race-resets-row").hidden = !live;
      text($("#race-closes-label"), live ? "Live event time" : "Closes");
      if (live) $("#race-closes").value = local(new Date(Date.now() + 3600000));
    }
    $$('[name="race-mode"]').forEach(function (r) { r.onchange = mode; });
    $("#race-ranking").onchange = function () {
      if ($("#race-ranking").value === "total_time") $("#race-min-laps").value = $("#race-max-laps").value;
    };
    $("#race-max-laps").oninput = function () {
      if ($("#race-ranking").value === "total_time") $("#race-min-laps").value = $("#race-max-laps").value;
    };
    kind();
    form.onsubmit = function (ev) {
      ev.preventDefault();
      var type = $("#race-type").value, race = { race_type: type };
      if (type === "object_avoidance") race.number_of_obstacles = Number($("#race-objects").value);
      if (type === "head_to_bot") race.number_of_bot_cars = Number($("#race-bots").value);
      var when = function (sel) { var v = $(sel).value; return v ? new Date(v).getTime() / 1000 : null; };
      var live = val("race-mode") === "live";
      var body = {
        mode: live ? "live" : "community", name: $("#race-name").value, description: $("#race-description").value, track: $("#race-track").value,
        reversed: val("race-direction") === "reversed", race: race, ranking: $("#race-ranking").value,
        min_laps: Number($("#race-min-laps").value), max_laps: Number($("#race-max-laps").value),
        off_track_penalty: Number($("#race-off-track").value), crash_penalty: Number($("#race-crash").value),
        max_submissions: Number($("#race-submissions").value), opens: when("#race-opens"), closes: when("#race-closes"),
      };
      // A window opening in the past minute opens now; a live race opens when it is made.
      if (live || (body.opens !== null && body.opens < Date.now() / 1000)) delete body.opens;
      if (live) body.max_resets = Number($("#race-resets").value);
      send("POST", "/api/v1/races", body).then(function (r) {
        if (r.ok) location.assign("/races/" + encodeURIComponent(r.v.name)); else showErrors($("#race-errors"), r.v);
      });
    };
  }
  function race() {
    var name = JSON.parse($("#race-json").textContent), base = "/api/v1/races/" + encodeURIComponent(name);
    function cell(tr, s) { tr.appendChild(text(document.createElement("td"), s)); return tr.lastChild; }
    var clock = clockOf;
    function refresh() {
      fetch(base + "/leaderboard", { credentials: "same-origin" }).then(function (r) { return r.json(); }).then(function (b) {
        var body = $("#leaderboard tbody");
        body.textContent = "";
        (b.rows || []).forEach(function (row) {
          var tr = document.createElement("tr");
          tr.dataset.racer = row.racer;
          cell(tr, String(row.rank)); cell(tr, row.racer); cell(tr, row.time); cell(tr, row.gap); cell(tr, String(row.off_tracks));
          var img = document.createElement("img");
          img.className = "lap";
          img.alt = "fastest lap of " + row.racer;
          img.src = base + "/entries/" + encodeURIComponent(row.entry) + "/lap.svg";
          cell(tr, "").appendChild(img);
          body.appendChild(tr);
        });
        if (!body.children.length) body.innerHTML = '<tr><td colspan="6" class="empty">No ranked entries yet.</td></tr>';
        text($("#evaluating"), b.evaluating ? b.evaluating + " entries being evaluated…" : "");
      });
      fetch(base + "/entries", { credentials: "same-origin" }).then(function (r) { return r.json(); }).then(function (list) {
        var body = $("#entries tbody");
        body.textContent = "";
        list.slice().reverse().forEach(function (e) {
          var tr = document.createElement("tr");
          tr.dataset.entry = e.id;
          cell(tr, e.model + (e.racer && e.racer !== e.model ? " (" + e.racer + ")" : ""));
          cell(tr, e.status === "done" ? (e.ranked ? clock(e.time_ms) : "not ranked") : "—");
          cell(tr, e.completed_laps === undefined ? "—" : String(e.completed_laps));
          var st = cell(tr, e.status === "failed" ? "failed: " + e.error : e.status);
          st.className = "entry-status";
          cell(tr, new Date(e.created * 1000).toLocaleString());
          body.appendChild(tr);
        });
        text($("#entry-count"), "(" + list.length + ")");
      });
    }
    refresh();
    setInterval(refresh, 3000);
    var form = $("#enter-race");
    if (form) form.onsubmit = function (ev) {
      ev.preventDefault();
      send("POST", base + "/entries", { model: $("#enter-model").value }).then(function (r) {
        if (r.ok) { $("#enter-errors").textContent = ""; refresh(); } else showErrors($("#enter-errors"), r.v);
      });
    };
    var del = $("#race-delete");
    if (del) del.onclick = function () {
      if (!confirm("Delete race " + name + " and its entries?")) return;
      send("DELETE", base).then(function (r) { if (r.ok) location.assign("/races"); else showErrors($("#enter-errors") || $("#evaluating"), r.v); });
    };
  }

  function clockOf(ms) {
    if (ms === null || ms === undefined) return "—";
    var m = Math.floor(ms / 60000), s = Math.floor(ms / 1000) % 60;
    return String(m).padStart(2, "0") + ":" + String(s).padStart(2, "0") + "." + String(ms % 1000).padStart(3, "0");
  }
  // ---- A live race: every viewer's page, and the facilitator's controls ----------------
  function live(manage) {
    var name = JSON.parse($("#race-json").textContent), base = "/api/v1/races/" + encodeURIComponent(name);
    var track = JSON.parse($("#track-json").textContent), car = null, last = null;
    fetch("/api/v1/tracks/" + encodeURIComponent(track) + "/picture.svg").then(function (r) { return r.text(); }).then(function (svg) {
      $("#live-track").innerHTML = svg;
      var s = $("#live-track svg");
      car = document.createElementNS("http://www.w3.org/2000/svg", "circle");
      car.setAttribute("r", "0.12"); car.setAttribute("fill", "#ec7211"); car.setAttribute("stroke", "#fff");
      car.setAttribute("stroke-width", "0.03"); car.setAttribute("id", "live-car"); car.style.display = "none";
      s.appendChild(car);
    });
    function act(body) {
      send("POST", base + "/live", body).then(function (r) {
        if (r.ok) { $("#live-errors").textContent = ""; show(r.v); } else showErrors($("#live-errors"), r.v);
      });
    }
    if (manage) {
      $("#live-launch").onclick = function () { act({ action: "launch" }); };
      $("#live-autolaunch").onchange = function () { act({ action: "autolaunch", on: this.checked }); };
      $("#live-submissions").onchange = function () { act({ action: "submissions", open: this.checked }); };
      $("#live-clear").onclick = function () { if (confirm("Clear the leaderboard?")) act({ action: "clear" }); };
      $("#live-winner").onclick = function () { act({ action: "winner" }); };
    }
    function show(v) {
      last = v;
      var c = v.current;
      var banner = v.phase === "completed" ? "The race is over" : c ? "Live" :
        v.phase === "scheduled" ? "Waiting for the facilitator to start the race" : "Waiting for the next racer";
      if (!v.submissions_open && v.phase !== "completed") banner += " · Submissions are closed";
      text($("#live-banner"), banner);
      text($("#now-racing"), c ? c.racer : "—");
      text($("#now-model"), c ? (c.model !== c.racer ? c.model + " " : "") + "(" + c.place + " of " + v.total + ")" : "");
      text($("#now-lap"), c && c.lap ? c.lap + " of " + c.laps : c && c.evaluating ? "starting…" : "—");
      text($("#now-time"), c && c.lap_s !== undefined ? c.lap_s.toFixed(1) + " s" : "—");
      text($("#now-progress"), c && c.progress !== undefined ? Math.round(c.progress) + " %" : "—");
      var laps = $("#now-laps");
      laps.textContent = "";
      ((c && c.lap_times) || []).forEach(function (t, i) { laps.appendChild(li("Lap " + (i + 1) + ": " + t)); });
      text($("#up-next"), v.up_next ? v.up_next.racer + " (" + v.up_next.model + ")" : "—");
      $("#race-progress").max = Math.max(1, v.total);
      $("#race-progress").value = v.evaluated;
      text($("#race-progress-text"), v.evaluated + " of " + v.total + " models evaluated");
      if (car) {
        if (c && c.at) { car.style.display = ""; car.setAttribute("cx", c.at[0]); car.setAttribute("cy", c.at[1]); }
        else car.style.display = "none";
      }
      var cam = $("#live-camera");
      if (c && c.camera) { cam.hidden = false; cam.src = base + "/live/camera.png?t=" + Date.now(); } else cam.hidden = true;
      var w = $("#winner");
      w.hidden = !v.winner;
      if (v.winner) { text($("#winner-name"), v.winner.racer + (v.winner.model !== v.winner.racer ? " (" + v.winner.model + ")" : "")); text($("#winner-time"), clockOf(v.winner.time_ms)); }
      var board = $("#live-board tbody");
      if (board) {
        board.textContent = "";
        v.leaderboard.slice(0, 10).forEach(function (row) {
          var tr = document.createElement("tr");
          [String(row.rank), row.racer, row.time, row.gap].forEach(function (s) { tr.appendChild(text(document.createElement("td"), s)); });
          board.appendChild(tr);
        });
      }
      var q = $("#queue tbody");
      if (q) {
        q.textContent = "";
        v.queue.forEach(function (e, i) {
          var tr = document.createElement("tr");
          tr.dataset.entry = e.entry;
          [String(e.place), e.racer, e.model, e.status.replace("_", " "), String(e.resets)].forEach(function (s) {
            tr.appendChild(text(document.createElement("td"), s));
          });
          if (manage) {
            var td = document.createElement("td");
            [["↑", { action: "move", entry: e.entry, to: Math.max(0, i - 1) }], ["↓", { action: "move", entry: e.entry, to: i + 1 }],
             ["Reset", { action: "reset", entry: e.entry }], ["Remove", { action: "remove", entry: e.entry }]].forEach(function (b) {
              var btn = text(document.createElement("button"), b[0]);
              btn.type = "button";
              btn.className = "queue-" + b[1].action + (b[0] === "↓" ? "-down" : b[0] === "↑" ? "-up" : "");
              btn.onclick = function () { if (b[1].action !== "remove" || confirm("Remove " + e.model + "?")) act(b[1]); };
              td.appendChild(btn);
            });
            tr.appendChild(td);
          }
          q.appendChild(tr);
        });
      }
      if (manage) {
        $("#live-autolaunch").checked = v.autolaunch;
        $("#live-submissions").checked = v.submissions_open;
        $("#live-launch").disabled = !!c || v.phase === "completed";
      }
    }
    function poll() {
      fetch(base + "/live", { credentials: "same-origin" }).then(function (r) { return r.json(); }).then(show).catch(function () {});
    }
    poll();
    setInterval(poll, 500);
    return function () { return last; };
  }

  // ---- The fleet -----------------------------------------------------------------------
  function cars() {
    var cfg = JSON.parse($("#cars-json").textContent), body = $("#cars tbody"), built = {};
    function order(car, o) {
      send("POST", "/api/v1/cars/" + encodeURIComponent(car), o).then(function (r) {
        if (r.ok) $("#car-errors").textContent = ""; else showErrors($("#car-errors"), r.v);
      });
    }
    function row(c) {
      var tr = document.createElement("tr");
      tr.dataset.car = c.car;
      for (var i = 0; i < 7; i++) tr.appendChild(document.createElement("td"));
      if (cfg.may_drive) {
        var td = document.createElement("td"), sel = document.createElement("select");
        sel.className = "car-model";
        sel.setAttribute("aria-label", "Model for " + c.car);
        cfg.models.forEach(function (m) { var o = text(document.createElement("option"), m); o.value = "model:" + m; sel.appendChild(o); });
        cfg.races.forEach(function (r) { var o = text(document.createElement("option"), "Live race " + r + ": the entry racing"); o.value = "race:" + r; sel.appendChild(o); });
        var go = text(document.createElement("button"), "Assign");
        go.type = "button"; go.className = "car-assign";
        go.onclick = function () {
          var v = sel.value, k = v.indexOf(":"), o = {};
          o[v.slice(0, k)] = v.slice(k + 1);
          order(c.car, o);
        };
        td.appendChild(sel); td.appendChild(go); tr.appendChild(td);
        var td2 = document.createElement("td");
        var stop = text(document.createElement("button"), "E-stop");
        stop.type = "button"; stop.className = "car-estop danger";
        stop.onclick = function () { order(c.car, { estop: true }); };
        var go2 = text(document.createElement("button"), "Release");
        go2.type = "button"; go2.className = "car-release";
        go2.onclick = function () { order(c.car, { estop: false }); };
        td2.appendChild(stop); td2.appendChild(go2); tr.appendChild(td2);
      }
      return tr;
    }
    function refresh() {
      fetch("/api/v1/cars", { credentials: "same-origin" }).then(function (r) { return r.json(); }).then(function (list) {
        var seen = {};
        if (list.length && !body.querySelector("tr[data-car]")) body.textContent = "";
        list.forEach(function (c) {
          seen[c.car] = true;
          var tr = built[c.car];
          if (!tr) { tr = built[c.car] = row(c); body.appendChild(tr); }
          var td = tr.children;
          text(td[0], c.car);
          text(td[1], c.model || c.job || "—");
          text(td[2], c.policy_version === null ? "—" : "v" + c.policy_version);
          text(td[3], c.frames_per_s.toFixed(1));
          text(td[4], c.latency_ms_p50.toFixed(2) + " / " + c.latency_ms_p99.toFixed(2) + " ms");
          text(td[5], String(c.refused) + (c.last_refusal ? " (" + c.last_refusal + ")" : ""));
          text(td[6], c.state);
          td[6].className = "car-state";
        });
        Object.keys(built).forEach(function (k) { if (!seen[k]) { built[k].remove(); delete built[k]; } });
        text($("#car-count"), "(" + list.length + ")");
      }).catch(function () {});
    }
    refresh();
    setInterval(refresh, 1000);
  }

  return { wizard: wizard, model: model, importer: importer, login: login, invite: invite, users: users, races: races, race: race, live: live, cars: cars };
})();
