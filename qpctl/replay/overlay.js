// qpctl replay: the panel beside viser's recorded scene (qpctl/replay/page.py).
// Reads window.__QPCTL_REPLAY__ (the run's title, frame times, colour scale, figure). Finds viser's
// playback bar (its time slider and time field), draws a cursor on the figure at the time shown,
// seeks where the figure is clicked, opens paused at ?t=SECONDS, and reports what it shows in
// window.qpctlReplay = {ready, time, frame, tick, seeked, canvas}.
(function () {
  "use strict";
  const cfg = window.__QPCTL_REPLAY__;
  const params = new URLSearchParams(window.location.search);
  const wanted = params.has("t") ? parseFloat(params.get("t")) : null;
  const state = (window.qpctlReplay = { ready: false, time: null, frame: null, tick: null, seeked: null, canvas: null });
  if (params.get("notices") === "0") document.documentElement.classList.add("qpctl-no-notices");

  function el(tag, attrs, children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (k === "text") e.textContent = v;
      else e.setAttribute(k, v);
    }
    for (const c of children || []) e.appendChild(c);
    return e;
  }

  function frameAt(t) {  // the last frame shown at or before t
    const times = cfg.frameTimes;
    let lo = 0, hi = times.length - 1;
    if (!(t >= times[0])) return 0;
    while (lo < hi) {
      const mid = (lo + hi + 1) >> 1;
      if (times[mid] <= t + 1e-9) lo = mid; else hi = mid - 1;
    }
    return lo;
  }

  function controls() {
    const slider = document.querySelector('[role="slider"][aria-valuemax]');
    const field = document.querySelector("input.mantine-NumberInput-input");
    return slider && field ? { slider, field } : null;
  }

  function seek(t) {  // through viser's own time field: it seeks and pauses
    const c = controls();
    if (!c) return false;
    const setter = Object.getOwnPropertyDescriptor(HTMLInputElement.prototype, "value").set;
    setter.call(c.field, String(Math.min(Math.max(t, 0), cfg.duration)));
    c.field.dispatchEvent(new Event("input", { bubbles: true }));
    return true;
  }

  function build() {
    const fig = cfg.figure;
    const cursor = el("div", { class: "qpctl-cursor" });
    const img = el("img", { src: "data:image/png;base64," + fig.png, alt: "clearance, tracking error, torque, QP status over time",
                            width: String(fig.width), height: String(fig.height) });
    const figBox = el("div", { class: "qpctl-figure", title: "click to show that moment" }, [img, cursor]);
    const bar = el("div", { class: "qpctl-scale-bar" });
    bar.style.background = "linear-gradient(to right, " + cfg.colours.neutral + " 0%, " + cfg.colours.neutral + " 8%, " +
      cfg.scale.map((s, i) => s[1] + " " + (8 + (84 * i) / (cfg.scale.length - 1)).toFixed(1) + "%").join(", ") + ", " +
      cfg.colours.contact + " 96%, " + cfg.colours.contact + " 100%)";
    const legend = el("div", { class: "qpctl-legend" }, [
      el("div", { class: "qpctl-scale-title", text: "link colour: clearance to the obstacles" }),
      bar,
      el("div", { class: "qpctl-scale-labels" }, [
        el("span", { text: "> d_influence " + cfg.dInfluence.toPrecision(3) + " m" }),
        el("span", { text: "d_safe " + cfg.dSafe.toPrecision(3) + " m" }),
        el("span", { text: "< 0" }),
      ]),
      el("div", { class: "qpctl-keys" }, [
        key(cfg.colours.reference, "reference path"), key(cfg.colours.trace, "task point's trace"),
        key(cfg.colours.marker, "task point"), key(cfg.colours.rigid, "rigid obstacle"), key(cfg.colours.soft, "soft obstacle"),
      ]),
    ]);
    const now = el("div", { class: "qpctl-now" });
    const panel = el("aside", { id: "qpctl-panel" }, [
      el("h1", { text: cfg.title }),
      el("div", { class: "qpctl-sub", text: cfg.robot + " · " + cfg.frameTimes.length + " frames at " + cfg.fps + "/s" }),
      now, legend, figBox,
      el("p", { class: "qpctl-help", text: "Space plays and pauses; the bar below the scene scrubs and sets the speed; " +
        "its last button lists the scene's parts (capsules hidden). Click the figure to show that moment; " +
        "add ?t=SECONDS to the address to open paused there." }),
    ]);
    const toggle = el("button", { id: "qpctl-toggle", type: "button", title: "figures", text: "◧" });
    toggle.addEventListener("click", () => document.documentElement.classList.toggle("qpctl-closed"));
    if (window.innerWidth < 1000) document.documentElement.classList.add("qpctl-closed");
    document.body.appendChild(panel);
    document.body.appendChild(toggle);
    figBox.addEventListener("click", (ev) => {
      const r = img.getBoundingClientRect();
      const x = (ev.clientX - r.left) / r.width;
      const t = fig.t0 + ((x - fig.left) / (fig.right - fig.left)) * (fig.t1 - fig.t0);
      if (t >= fig.t0 - 1e-9 && t <= fig.t1 + 1e-9) seek(t);
    });
    return { cursor, img, now };
  }

  function key(colour, label) {
    const dot = el("span", { class: "qpctl-dot" });
    dot.style.background = colour;
    return el("span", { class: "qpctl-key" }, [dot, document.createTextNode(label)]);
  }

  function start() {
    const ui = build();
    const fig = cfg.figure;
    let found = null, seekAt = null, frames = 0, since = 0;
    function tick() {
      const c = controls();
      if (c) {
        if (!found) { found = performance.now(); state.controlsAt = Math.round(found); }
        if (wanted !== null && state.seeked === null && seek(wanted)) { state.seeked = wanted; seekAt = performance.now(); frames = 0; }
        const t = parseFloat(c.slider.getAttribute("aria-valuenow"));
        if (Number.isFinite(t)) {
          state.time = t;
          state.frame = frameAt(t);
          state.tick = cfg.frameTicks[state.frame];
          const x = fig.left + ((t - fig.t0) / (fig.t1 - fig.t0)) * (fig.right - fig.left);
          ui.cursor.style.left = (100 * x).toFixed(3) + "%";
          ui.cursor.style.top = (100 * fig.top).toFixed(3) + "%";
          ui.cursor.style.height = (100 * (fig.bottom - fig.top)).toFixed(3) + "%";
          ui.now.textContent = "t = " + t.toFixed(2) + " s · frame " + state.frame + " · sample " + state.tick;
        }
        const canvas = document.querySelector("canvas");
        if (canvas) {
          const r = canvas.getBoundingClientRect();
          state.canvas = { x: r.x, y: r.y, width: r.width, height: r.height };
        }
        frames += 1;
        // drawn: a few frames after the controls appeared (playing), or after the seek took effect
        const onTime = wanted === null || (state.seeked !== null && Math.abs(state.time - wanted) < 5e-3);
        since = onTime ? since + 1 : 0;
        const settled = since > 6 && performance.now() - (seekAt || found) > 500;
        if (settled && !state.ready) { state.ready = true; state.readyAt = Math.round(performance.now()); state.frames = frames; }
      }
      window.requestAnimationFrame(tick);
    }
    window.requestAnimationFrame(tick);
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
