(function () {
  "use strict";
  var DATA = JSON.parse(document.getElementById("motion-data").textContent);
  var fps = DATA.fps, J = DATA.joints, cam = DATA.camera, bones = DATA.bones;
  var speed = 1, loop = true, players = [];
  var dpr = Math.max(1, window.devicePixelRatio || 1);

  function dot(p, v) { return p[0] * v[0] + p[1] * v[1] + p[2] * v[2]; }

  function Player(card, m) {
    var self = this;
    this.card = card; this.m = m; this.L = m.frames;
    this.canvas = card.querySelector("canvas");
    this.ctx = this.canvas.getContext("2d");
    this.canvas.width = Math.round(this.canvas.width * dpr);
    this.canvas.height = Math.round(this.canvas.height * dpr);
    this.W = this.canvas.width / dpr; this.H = this.canvas.height / dpr;
    this.button = card.querySelector("button.play");
    this.scrub = card.querySelector("input.scrub");
    this.label = card.querySelector(".frame");
    this.segmentItems = card.querySelectorAll("ol.segments li");
    // Image-plane points (x right, y up), depth along the view, per frame and joint; the root on the floor.
    var n = this.L * J, xy = new Float32Array(2 * n), depth = new Float32Array(n), centre = new Float32Array(2 * this.L);
    var p = [0, 0, 0];
    for (var i = 0; i < n; i++) {
      p[0] = m.joints[3 * i]; p[1] = m.joints[3 * i + 1]; p[2] = m.joints[3 * i + 2];
      xy[2 * i] = dot(p, cam.right); xy[2 * i + 1] = dot(p, cam.up); depth[i] = dot(p, cam.look);
    }
    for (var f = 0; f < this.L; f++) {
      p[0] = m.joints[3 * f * J]; p[1] = m.floor; p[2] = m.joints[3 * f * J + 2];
      centre[2 * f] = dot(p, cam.right); centre[2 * f + 1] = dot(p, cam.up);
    }
    this.xy = xy; this.depth = depth; this.centre = centre;
    // Floor grid lines x = k·s and z = k·s over the ground the root covers (fixed in the world).
    var g = m.grid, s = DATA.gridSpacing, lines = [];
    function seg(a, b) {
      lines.push([dot(a, cam.right), dot(a, cam.up), dot(b, cam.right), dot(b, cam.up)]);
    }
    for (var k = Math.ceil(g[0] / s); k * s <= g[2]; k++) seg([k * s, m.floor, g[1]], [k * s, m.floor, g[3]]);
    for (k = Math.ceil(g[1] / s); k * s <= g[3]; k++) seg([g[0], m.floor, k * s], [g[2], m.floor, k * s]);
    this.grid = lines;
    this.order = bones.map(function (_, b) { return b; });
    // The clock starts now (not at the first animation frame: a headless browser may render very few).
    this.frame = 0; this.playing = true; this.origin = performance.now(); this.visible = true; this.drawn = -1;
    this.button.addEventListener("click", function () { self.toggle(); });
    this.canvas.addEventListener("click", function () { self.toggle(); });
    this.scrub.addEventListener("input", function () {
      self.setPlaying(false); self.frame = Number(self.scrub.value); self.draw();
    });
  }

  Player.prototype.setPlaying = function (on) {
    if (on && !loop && this.frame >= this.L - 1) this.frame = 0;  // play again from the start
    this.playing = on; this.origin = null;
    this.button.textContent = on ? "Pause" : "Play";
  };
  Player.prototype.toggle = function () { this.setPlaying(!this.playing); updateAllButton(); };

  Player.prototype.advance = function (now) {
    if (!this.playing) return;
    if (this.origin === null) this.origin = now - this.frame / (fps * speed) * 1000;
    var f = Math.floor((now - this.origin) / 1000 * fps * speed);
    if (f >= this.L) {
      if (loop) { f = f % this.L; } else { f = this.L - 1; this.frame = f; this.setPlaying(false); updateAllButton(); }
    }
    this.frame = f;
  };

  Player.prototype.draw = function () {
    var c = this.ctx, m = this.m, f = this.frame, W = this.W, H = this.H, v = m.view, xy = this.xy;
    var cx = this.centre[2 * f], cy = this.centre[2 * f + 1];
    var x0 = cx + v[0], y0 = cy + v[1], scale = Math.min(W / (v[2] - v[0]), H / (v[3] - v[1]));
    function X(x) { return (x - x0) * scale; }
    function Y(y) { return H - (y - y0) * scale; }
    c.setTransform(dpr, 0, 0, dpr, 0, 0);
    c.fillStyle = "#ffffff"; c.fillRect(0, 0, W, H);
    c.lineCap = "round"; c.lineJoin = "round";
    c.strokeStyle = DATA.floorColor; c.lineWidth = 0.7; c.beginPath();
    for (var i = 0; i < this.grid.length; i++) {
      var l = this.grid[i]; c.moveTo(X(l[0]), Y(l[1])); c.lineTo(X(l[2]), Y(l[3]));
    }
    c.stroke();
    c.strokeStyle = DATA.trajectoryColor; c.lineWidth = 1.3; c.beginPath();
    for (var t = 0; t <= f; t++) {
      var px = X(this.centre[2 * t]), py = Y(this.centre[2 * t + 1]);
      if (t === 0) c.moveTo(px, py); else c.lineTo(px, py);
    }
    c.stroke();
    // Painter's order: farther bones first.
    var base = f * J, depth = this.depth, order = this.order;
    order.sort(function (a, b) {
      var da = depth[base + bones[a][0]] + depth[base + bones[a][1]], db = depth[base + bones[b][0]] + depth[base + bones[b][1]];
      return db - da;
    });
    c.lineWidth = 3;
    for (var o = 0; o < order.length; o++) {
      var b = order[o], pa = base + bones[b][0], pb = base + bones[b][1];
      c.strokeStyle = m.edited ? (m.edited.charAt(pb) === "1" ? DATA.editedColor : DATA.keptColor) : DATA.boneColors[b];
      c.beginPath(); c.moveTo(X(xy[2 * pa]), Y(xy[2 * pa + 1])); c.lineTo(X(xy[2 * pb]), Y(xy[2 * pb + 1])); c.stroke();
    }
    c.fillStyle = "#6e7781"; c.font = "11px system-ui, sans-serif";
    c.fillText((f + 1) + "/" + this.L, 6, H - 6);
    this.scrub.value = String(f);
    this.label.textContent = (f + 1) + "/" + this.L + " · " + (f / fps).toFixed(2) + " s";
    for (var s = 0; s < this.segmentItems.length; s++) {
      var item = this.segmentItems[s], on = f >= Number(item.dataset.start) && f < Number(item.dataset.end);
      if (item.classList.contains("current") !== on) item.classList.toggle("current", on);
    }
    this.card.setAttribute("data-frame", String(f));
    this.drawn = f;
  };

  var allButton = document.getElementById("all");
  function updateAllButton() {
    var any = players.some(function (p) { return p.playing; });
    allButton.textContent = any ? "Pause all" : "Play all";
  }
  allButton.addEventListener("click", function () {
    var any = players.some(function (p) { return p.playing; });
    players.forEach(function (p) { p.setPlaying(!any); });
    updateAllButton();
  });
  document.getElementById("loop").addEventListener("change", function (e) {
    loop = e.target.checked;
    players.forEach(function (p) { p.origin = null; });
  });
  document.getElementById("speed").addEventListener("change", function (e) {
    speed = Number(e.target.value) || 1;
    players.forEach(function (p) { p.origin = null; });
  });

  var byIndex = {};
  DATA.motions.forEach(function (m) { byIndex[m.index] = m; });
  document.querySelectorAll("section.card").forEach(function (card) {
    var m = byIndex[Number(card.dataset.index)];
    if (m && card.querySelector("canvas")) players.push(new Player(card, m));
  });
  if ("IntersectionObserver" in window) {  // only figures on screen are drawn
    var observer = new IntersectionObserver(function (entries) {
      entries.forEach(function (e) { e.target.player.visible = e.isIntersecting; if (e.isIntersecting) e.target.player.drawn = -1; });
    });
    players.forEach(function (p) { p.canvas.player = p; observer.observe(p.canvas); });
  }
  players.forEach(function (p) { p.draw(); });
  function tick() {
    var now = performance.now();  // the current time, not the frame's start (the same in a browser on screen)
    for (var i = 0; i < players.length; i++) {
      var p = players[i];
      p.advance(now);
      if (p.visible && p.drawn !== p.frame) p.draw();
    }
    window.requestAnimationFrame(tick);
  }
  window.requestAnimationFrame(tick);
  document.documentElement.setAttribute("data-ready", String(players.length));
})();
