/* modi 3D motion viewer: own perspective projection on a 2D canvas (no WebGL, no libraries, no network).
   Data: JSON in #modi-data (see modi/viz/viewer.py); positions are int16 per motion with an origin and a step. */
(function () {
  'use strict';
  var D = JSON.parse(document.getElementById('modi-data').textContent);
  var q = new URLSearchParams(window.location.search);
  var canvas = document.getElementById('view'), ctx = canvas.getContext('2d');
  var tip = document.getElementById('tip'), stage = document.getElementById('stage');
  var playBtn = document.getElementById('play'), scrub = document.getElementById('scrub');
  var frameLabel = document.getElementById('frame'), speedSel = document.getElementById('speed');
  var layoutSel = document.getElementById('layout'), followBox = document.getElementById('follow');
  var legend = document.getElementById('legend');
  var FOV = 40 * Math.PI / 180, NEAR = 0.05;

  function bytes(b64) {
    var s = atob(b64), out = new Uint8Array(s.length);
    for (var i = 0; i < s.length; i++) out[i] = s.charCodeAt(i);
    return out;
  }

  // ---------------------------------------------------------------------------------------------- decoding
  var motions = D.motions.map(function (m) {
    var raw = bytes(m.pos), dv = new DataView(raw.buffer), n = m.frames * m.names.length * 3;
    var pos = new Float32Array(n);
    for (var i = 0; i < n; i++) pos[i] = m.origin[i % 3] + (dv.getInt16(2 * i, true) + 32768) * m.step;
    var con = null;
    if (m.contacts) {
      var bits = bytes(m.contacts);
      con = new Uint8Array(m.frames * m.names.length);
      for (var k = 0; k < con.length; k++) con[k] = (bits[k >> 3] >> (7 - (k & 7))) & 1;
    }
    return {title: m.title, names: m.names, parents: m.parents, side: m.side, hide: m.hide, fps: m.fps, T: m.frames,
            J: m.names.length, pos: pos, con: con, off: [0, 0, 0], color: D.colors[m.color % D.colors.length],
            height: m.height, small: m.small || [], duration: (m.frames - 1) / m.fps};
  });
  var fpsMaster = Math.max.apply(null, motions.map(function (m) { return m.fps; }));
  var nFrames = 1 + Math.round(Math.max.apply(null, motions.map(function (m) {
    return (m.T - 1) / m.fps; })) * fpsMaster);
  var hMax = Math.max.apply(null, D.motions.map(function (m) { return m.height; }));

  function frameOf(m, f) { return Math.min(m.T - 1, Math.round(f / fpsMaster * m.fps)); }
  function ended(m, f) { return f / fpsMaster > m.duration + 0.5 / m.fps; }  // holds its last pose from then
  function joint(m, t, j) {
    var i = (t * m.J + j) * 3;
    return [m.pos[i] + m.off[0], m.pos[i + 1], m.pos[i + 2] + m.off[2]];
  }

  // ---------------------------------------------------------------------------------------------- layout
  var box;  // scene bounds over all frames (with layout offsets)
  function bounds(m) {
    var lo = [Infinity, Infinity, Infinity], hi = [-Infinity, -Infinity, -Infinity];
    for (var i = 0; i < m.pos.length; i++) {
      var k = i % 3;
      if (m.pos[i] < lo[k]) lo[k] = m.pos[i];
      if (m.pos[i] > hi[k]) hi[k] = m.pos[i];
    }
    return [lo, hi];
  }
  motions.forEach(function (m) {
    m.bounds = bounds(m);
    m.centre = Math.max(0, m.hide.indexOf(1));  // the hips when the root is a floor marker, else the root
    m.marker = m.hide.map(function () { return 0; });
    m.hide.forEach(function (h, j) { if (h) m.marker[m.parents[j]] = 1; });
    // a cell's follow camera: the centre joint's ground track averaged over a second (no per-step sway)
    // (x, z, and y above the clip's median: a jump lifts the camera with the body)
    var k = Math.max(1, Math.round(0.25 * m.fps)), cx = [], cz = [], cy = [];
    for (var t = 0; t < m.T; t++) {
      var i = (t * m.J + m.centre) * 3;
      cx.push(m.pos[i]); cy.push(m.pos[i + 1]); cz.push(m.pos[i + 2]);
    }
    var ymid = cy.slice().sort(function (p, r) { return p - r; })[Math.floor(m.T / 2)];
    m.track = [];
    for (t = 0; t < m.T; t++) {
      var a = Math.max(0, t - k), b = Math.min(m.T - 1, t + k), sx = 0, sz = 0, sy = 0;
      for (var u = a; u <= b; u++) { sx += cx[u]; sz += cz[u]; sy += cy[u]; }
      m.track.push([sx / (b - a + 1), sz / (b - a + 1), Math.max(0, sy / (b - a + 1) - ymid)]);
    }
  });
  // small multiples (side by side): one cell per motion, each with its own camera; one motion is one cell too,
  // unless it is shown with a still camera (follow off), which frames the ground it covers instead
  function cellMode() { return layoutSel.value === 'grid' && (motions.length > 1 || followBox.checked); }
  var cells = {cols: 1, rows: 1, w: 1, h: 1};
  function layoutCells() {  // small multiples: the column count that gives each figure the most height
    var n = motions.length, best = -1;
    for (var c = 1; c <= n; c++) {
      var r = Math.ceil(n / c), w = W / c, h = H / r, score = Math.min(h, 1.6 * w);
      if (score > best + 1e-9) { best = score; cells = {cols: c, rows: r, w: w, h: h}; }
    }
  }
  function applyLayout() {  // one scene: every motion where it is; small multiples: each cell follows its figure
    motions.forEach(function (m) { m.off = [0, 0, 0]; });
    box = [[Infinity, 0, Infinity], [-Infinity, hMax, -Infinity]];
    motions.forEach(function (m) {
      for (var k = 0; k < 3; k += 2) {
        box[0][k] = Math.min(box[0][k], m.bounds[0][k] + m.off[k]);
        box[1][k] = Math.max(box[1][k], m.bounds[1][k] + m.off[k]);
      }
      box[1][1] = Math.max(box[1][1], m.bounds[1][1]);
    });
  }

  // ---------------------------------------------------------------------------------------------- camera
  var cam = {};
  function groupCentre(f) {  // mean ground position of the bodies at frame f (what 'follow' looks at)
    var sx = 0, sz = 0;
    motions.forEach(function (m) { var c = joint(m, frameOf(m, f), m.centre); sx += c[0]; sz += c[2]; });
    return [sx / motions.length, sz / motions.length];
  }
  function fitDistance() {
    var r;
    if (followBox.checked) {  // the group around its moving centre, not the ground it covers
      r = 0;
      for (var f = 0; f < nFrames; f += Math.max(1, Math.floor(nFrames / 200))) {
        var g = groupCentre(f);
        motions.forEach(function (m) {
          var c = joint(m, frameOf(m, f), m.centre);
          r = Math.max(r, Math.sqrt((c[0] - g[0]) * (c[0] - g[0]) + (c[2] - g[1]) * (c[2] - g[1])));
        });
      }
      r = Math.sqrt((r + 0.6 * hMax) * (r + 0.6 * hMax) + 0.25 * hMax * hMax) + 0.1 * hMax;
      cam.dist = r / Math.sin(FOV / 2);
    } else {
      var dx = box[1][0] - box[0][0], dy = box[1][1] - box[0][1], dz = box[1][2] - box[0][2];
      r = 0.5 * Math.sqrt(dx * dx + dy * dy + dz * dz) + 0.1 * hMax;
      cam.dist = 0.8 * r / Math.sin(FOV / 2);  // the scene is flat: the bounding sphere over-fits
    }
  }
  function resetCamera() {
    cam.target = [(box[0][0] + box[1][0]) / 2, 0.45 * box[1][1], (box[0][2] + box[1][2]) / 2];
    cam.home = cam.target.slice();
    fitDistance();
    cam.dist0 = cam.dist;
    cam.az = num('az', 35) * Math.PI / 180;
    cam.el = num('el', 18) * Math.PI / 180;
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function unit(a) { var l = Math.sqrt(dot(a, a)) || 1; return [a[0] / l, a[1] / l, a[2] / l]; }
  var W = 1, H = 1, view = {};
  function setupView(target) {
    var ce = Math.cos(cam.el);
    var dir = [ce * Math.sin(cam.az), Math.sin(cam.el), ce * Math.cos(cam.az)];
    view.eye = [target[0] + cam.dist * dir[0], target[1] + cam.dist * dir[1], target[2] + cam.dist * dir[2]];
    view.f = unit(sub(target, view.eye));
    view.r = unit(cross(view.f, [0, 1, 0]));
    view.u = cross(view.r, view.f);
    view.fpx = (H / 2) / Math.tan(FOV / 2);
  }
  function toCam(p) { var d = sub(p, view.eye); return [dot(d, view.r), dot(d, view.u), dot(d, view.f)]; }
  function project(c) { return [W / 2 + view.fpx * c[0] / c[2], H / 2 - view.fpx * c[1] / c[2], c[2]]; }
  function segment(a, b) {  // camera-space segment clipped at the near plane, projected; null when behind
    var ca = toCam(a), cb = toCam(b);
    if (ca[2] < NEAR && cb[2] < NEAR) return null;
    if (ca[2] < NEAR || cb[2] < NEAR) {
      var s = (NEAR - ca[2]) / (cb[2] - ca[2]), m = [0, 0, NEAR];
      m[0] = ca[0] + s * (cb[0] - ca[0]); m[1] = ca[1] + s * (cb[1] - ca[1]);
      if (ca[2] < NEAR) ca = m; else cb = m;
    }
    return [project(ca), project(cb)];
  }

  // ---------------------------------------------------------------------------------------------- drawing
  var frame = 0, playing = true, speed = 1, hover = null, drawn = [];
  function niceStep(x) {
    var e = Math.pow(10, Math.floor(Math.log10(x)));
    return [1, 2, 5, 10].map(function (v) { return v * e; }).reduce(function (a, b) {
      return Math.abs(Math.log(b / x)) < Math.abs(Math.log(a / x)) ? b : a; });
  }
  function line(a, b, color, width) {
    var s = segment(a, b);
    if (!s) return;
    ctx.strokeStyle = color; ctx.lineWidth = width;
    ctx.beginPath(); ctx.moveTo(s[0][0], s[0][1]); ctx.lineTo(s[1][0], s[1][1]); ctx.stroke();
  }
  function drawGrid() {
    var step = niceStep(hMax / 2), pad = 2 * step;
    var x0 = Math.floor((box[0][0] - pad) / step) * step, x1 = Math.ceil((box[1][0] + pad) / step) * step;
    var z0 = Math.floor((box[0][2] - pad) / step) * step, z1 = Math.ceil((box[1][2] + pad) / step) * step;
    for (var x = x0; x <= x1 + 1e-9; x += step) line([x, 0, z0], [x, 0, z1], D.style.grid, 1);
    for (var z = z0; z <= z1 + 1e-9; z += step) line([x0, 0, z], [x1, 0, z], D.style.grid, 1);
  }
  function ring(p, radius, color) {  // a circle on the ground around p
    ctx.strokeStyle = color; ctx.lineWidth = 2; ctx.beginPath();
    var first = true;
    for (var i = 0; i <= 16; i++) {
      var a = i / 16 * 2 * Math.PI, c = toCam([p[0] + radius * Math.cos(a), 0, p[2] + radius * Math.sin(a)]);
      if (c[2] < NEAR) { first = true; continue; }
      var s = project(c);
      if (first) ctx.moveTo(s[0], s[1]); else ctx.lineTo(s[0], s[1]);
      first = false;
    }
    ctx.stroke();
  }
  function drawGridAround(target, radius, step) {
    var x0 = Math.floor((target[0] - radius) / step) * step, x1 = Math.ceil((target[0] + radius) / step) * step;
    var z0 = Math.floor((target[2] - radius) / step) * step, z1 = Math.ceil((target[2] + radius) / step) * step;
    for (var x = x0; x <= x1 + 1e-9; x += step) line([x, 0, z0], [x, 0, z1], D.style.grid, 1);
    for (var z = z0; z <= z1 + 1e-9; z += step) line([x0, 0, z], [x1, 0, z], D.style.grid, 1);
  }
  function cellDistance(m, travel) {  // the figure fills ~70 % of its cell's height (90 % of its width at most)
    var th = 2 * Math.tan(FOV / 2), aspect = cells.w / cells.h, wide = Math.max(0.8 * m.height, travel);
    return Math.max(m.height / (0.7 * th), wide / (0.9 * th * aspect)) + 0.3 * m.height;
  }
  var cellView = [];  // per motion: the view its cell was drawn with (for hover and screenOf)
  function drawFigure(m, mi, P, t, bones, scale) {
    for (var j = 0; j < m.J; j++) {  // floor shadow first: it lies under everything
      var p = m.parents[j];
      if (p >= 0 && !m.hide[j]) line([P[p][0], 0, P[p][2]], [P[j][0], 0, P[j][2]], D.style.shadow, 3);
    }
    for (j = 0; j < m.J; j++) {
      var c = toCam(P[j]);
      var on = m.con ? m.con[t * m.J + j] === 1 : false;
      if (on) ring(P[j], 0.04 * scale, D.style.contactRing);
      if (c[2] > NEAR && !m.marker[j]) drawn.push({m: mi, j: j, s: project(c), on: on, depth: c[2], ox: view.ox,
                                                   oy: view.oy, small: m.small[j] === 1});
      p = m.parents[j];
      if (p >= 0 && !m.hide[j]) bones.push({a: P[p], b: P[j], color: m.color[m.side[j]],
                                            depth: (toCam(P[p])[2] + c[2]) / 2, small: m.small[j] === 1});
    }
  }
  function drawBones(bones, scale) {
    bones.sort(function (a, b) { return b.depth - a.depth; });
    bones.forEach(function (b) {
      var w = Math.max(1.5, Math.min(9, 0.035 * scale * view.fpx / Math.max(b.depth, NEAR)));
      line(b.a, b.b, b.color, b.small ? Math.max(1, 0.4 * w) : w);
    });
  }
  function drawJoints(list, scale) {
    list.forEach(function (d) {
      var m = motions[d.m], r = Math.max(1.5, Math.min(7, 0.02 * scale * view.fpx / d.depth)) * (d.on ? 1.8 : 1);
      if (d.small && !d.on) r = Math.max(0.8, 0.35 * r);  // fingers: small, a hand is not a blob
      ctx.fillStyle = d.on ? D.style.contact : m.color[m.side[d.j]];
      ctx.beginPath(); ctx.arc(d.s[0], d.s[1], r, 0, 2 * Math.PI); ctx.fill();
    });
  }
  function label(m, x, y, maxw) {  // the motion's title, and whether it has ended (it then holds its last pose)
    var text = m.title + (ended(m, frame) ? ' · ended (last pose held)' : '');
    while (text.length > 1 && ctx.measureText(text).width > maxw) text = text.slice(0, -2) + '…';
    ctx.fillStyle = ended(m, frame) ? '#8a8a8a' : D.style.text;
    ctx.fillText(text, x, y);
  }
  function drawCells() {
    layoutCells();
    drawn = [];
    cellView = [];
    var W0 = W, H0 = H, zoom = cam.dist / cam.dist0;
    ctx.font = '12px sans-serif'; ctx.textAlign = 'left';
    motions.forEach(function (m, mi) {
      var c = mi % cells.cols, r = Math.floor(mi / cells.cols), x0 = Math.round(c * cells.w),
          y0 = Math.round(r * cells.h), w = Math.round((c + 1) * cells.w) - x0, h = Math.round((r + 1) * cells.h) - y0;
      var t = frameOf(m, frame), tr = m.track[t], b = m.bounds;
      if (!followBox.checked) tr = [(b[0][0] + b[1][0]) / 2, (b[0][2] + b[1][2]) / 2];  // a still cell camera
      ctx.save();
      ctx.beginPath(); ctx.rect(x0, y0, w, h); ctx.clip();
      ctx.translate(x0, y0);
      W = w; H = h;
      var dist = cam.dist;
      cam.dist = cellDistance(m, followBox.checked ? 0 : Math.max(b[1][0] - b[0][0], b[1][2] - b[0][2])) * zoom;
      var lift = followBox.checked ? m.track[t][2] : 0;
      var target = [tr[0] + cam.target[0] - cam.home[0], 0.45 * m.height + lift + cam.target[1] - cam.home[1],
                    tr[1] + cam.target[2] - cam.home[2]];
      setupView(target);
      view.ox = x0; view.oy = y0;
      cellView[mi] = {eye: view.eye, f: view.f, r: view.r, u: view.u, fpx: view.fpx, W: w, H: h, ox: x0, oy: y0};
      drawGridAround(target, 2.5 * m.height, niceStep(m.height / 2));
      var P = [], bones = [], first = drawn.length;
      for (var j = 0; j < m.J; j++) P.push(joint(m, t, j));
      drawFigure(m, mi, P, t, bones, m.height);
      drawBones(bones, m.height);
      drawJoints(drawn.slice(first), m.height);
      cam.dist = dist;
      ctx.strokeStyle = '#c8c8c2'; ctx.lineWidth = 1; ctx.strokeRect(0.5, 0.5, w - 1, h - 1);
      label(m, 6, 15, w - 12);
      ctx.restore();
      drawn.slice(first).forEach(function (d) { d.s = [d.s[0] + x0, d.s[1] + y0]; });
    });
    W = W0; H = H0;
  }
  function draw() {
    var dpr = window.devicePixelRatio || 1;
    W = stage.clientWidth; H = stage.clientHeight;
    if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
      canvas.width = Math.round(W * dpr); canvas.height = Math.round(H * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = D.style.background; ctx.fillRect(0, 0, W, H);
    if (cellMode()) { drawCells(); finishDraw(); return; }
    var target = cam.target;
    if (followBox.checked) {  // the group's centre, shifted by any pan since the reset
      var g = groupCentre(frame);
      target = [g[0] + cam.target[0] - cam.home[0], cam.target[1], g[1] + cam.target[2] - cam.home[2]];
    }
    setupView(target);
    view.ox = view.oy = 0;
    drawGrid();
    var bones = [];
    drawn = [];
    motions.forEach(function (m, mi) {
      var t = frameOf(m, frame), P = [];
      for (var j = 0; j < m.J; j++) P.push(joint(m, t, j));
      drawFigure(m, mi, P, t, bones, hMax);
    });
    drawBones(bones, hMax);
    drawJoints(drawn, hMax);
    finishDraw();
  }
  function finishDraw() {
    if (hover) {
      var hd = pick(hover[0], hover[1]);
      if (hd) {
        ctx.strokeStyle = D.style.text; ctx.lineWidth = 1.5;
        ctx.beginPath(); ctx.arc(hd.s[0], hd.s[1], 9, 0, 2 * Math.PI); ctx.stroke();
        var hm = motions[hd.m];
        tip.textContent = (motions.length > 1 ? hm.title + ' \u00b7 ' : '') + hm.names[hd.j] + (hd.on ? ' (contact)' : '');
        tip.style.left = (hd.s[0] + 12) + 'px'; tip.style.top = (hd.s[1] - 8) + 'px'; tip.style.display = 'block';
      } else tip.style.display = 'none';
    }
    scrub.value = frame;
    var m0 = motions[0];  // the frame number is the first motion's; the time is everyone's
    frameLabel.textContent = 'frame ' + frameOf(m0, frame) + ' / ' + (m0.T - 1) + ' \u00b7 ' +
        (frame / fpsMaster).toFixed(2) + ' s';
    legendEnded();
  }
  function pick(x, y) {  // nearest drawn joint within 10 px, the front one on ties
    var best = null, bd = 100;
    drawn.forEach(function (d) {
      var e = (d.s[0] - x) * (d.s[0] - x) + (d.s[1] - y) * (d.s[1] - y);
      if (e < bd || (best && e === bd && d.depth < best.depth)) { bd = e; best = d; }
    });
    return best;
  }

  // ---------------------------------------------------------------------------------------------- controls
  function num(name, dflt) { var v = parseFloat(q.get(name)); return isFinite(v) ? v : dflt; }
  function setPlaying(p) { playing = p; playBtn.textContent = p ? 'pause' : 'play'; last = null; }
  var last = null, clock = 0;
  function tick(now) {
    if (playing) {
      if (last !== null) clock += (now - last) / 1000 * speed;
      frame = Math.floor(clock * fpsMaster) % nFrames;
      draw();
    }
    last = now;
    window.requestAnimationFrame(tick);
  }
  function seek(f) { frame = Math.max(0, Math.min(nFrames - 1, f | 0)); clock = frame / fpsMaster; draw(); }
  playBtn.addEventListener('click', function () { setPlaying(!playing); });
  scrub.addEventListener('input', function () { setPlaying(false); seek(parseInt(scrub.value, 10)); });
  speedSel.addEventListener('change', function () { speed = parseFloat(speedSel.value); });
  layoutSel.addEventListener('change', function () { applyLayout(layoutSel.value); resetCamera(); draw(); });
  followBox.addEventListener('change', function () { fitDistance(); cam.dist0 = cam.dist; draw(); });
  window.addEventListener('keydown', function (e) {
    if (/^(BUTTON|INPUT|SELECT)$/.test(e.target.tagName)) return;  // the control handles its own keys
    if (e.key === ' ') { setPlaying(!playing); e.preventDefault(); }
    else if (e.key === 'ArrowRight') { setPlaying(false); seek(frame + 1); }
    else if (e.key === 'ArrowLeft') { setPlaying(false); seek(frame - 1); }
  });
  var drag = null;
  canvas.addEventListener('pointerdown', function (e) {
    drag = {x: e.clientX, y: e.clientY, pan: e.shiftKey || e.button !== 0};
    canvas.setPointerCapture(e.pointerId);
  });
  canvas.addEventListener('pointerup', function () { drag = null; });
  canvas.addEventListener('pointermove', function (e) {
    var rect = canvas.getBoundingClientRect();
    hover = [e.clientX - rect.left, e.clientY - rect.top];
    if (drag) {
      var dx = e.clientX - drag.x, dy = e.clientY - drag.y;
      drag.x = e.clientX; drag.y = e.clientY;
      if (drag.pan) {
        var k = cam.dist * 0.0015;
        for (var i = 0; i < 3; i++) cam.target[i] += -dx * k * view.r[i] + dy * k * view.u[i];
      } else {
        cam.az -= dx * 0.008;
        cam.el = Math.max(-0.2, Math.min(1.5, cam.el + dy * 0.008));
      }
    }
    draw();
  });
  canvas.addEventListener('pointerleave', function () { hover = null; tip.style.display = 'none'; draw(); });
  canvas.addEventListener('contextmenu', function (e) { e.preventDefault(); });
  canvas.addEventListener('wheel', function (e) {
    cam.dist = Math.max(0.2 * hMax, cam.dist * Math.exp(e.deltaY * 0.001));
    e.preventDefault(); draw();
  }, {passive: false});
  canvas.addEventListener('dblclick', function () { resetCamera(); draw(); });
  window.addEventListener('resize', draw);

  // ---------------------------------------------------------------------------------------------- start
  scrub.max = nFrames - 1;
  layoutSel.value = q.get('layout') === 'scene' || q.get('layout') === 'grid' ? q.get('layout') : D.layout;
  speed = num('speed', 1); speedSel.value = String(speed);
  if (speedSel.value !== String(speed)) {
    var opt = document.createElement('option'); opt.value = opt.textContent = String(speed);
    speedSel.appendChild(opt); speedSel.value = String(speed);
  }
  var legendItems = [];
  [['left', D.colors[0][1]], ['right', D.colors[0][2]], ['contact', D.style.contact]].forEach(function (e) {
    var item = document.createElement('span'), sw = document.createElement('i');
    sw.style.background = e[1]; item.appendChild(sw);
    item.appendChild(document.createTextNode(e[0]));
    item.className = 'key';
    legend.appendChild(item);
  });
  motions.forEach(function (m) {  // the motions' own colours (hidden in small multiples: each cell is labelled)
    var item = document.createElement('span'), sw = document.createElement('i');
    sw.style.background = m.color[0]; item.appendChild(sw);
    item.appendChild(document.createTextNode(m.title));
    item.className = 'motion';
    legend.appendChild(item);
    legendItems.push(item);
  });
  function legendEnded() {  // in the legend too: a clip that has ended is greyed (it holds its last pose)
    legendItems.forEach(function (item, i) {
      item.style.display = cellMode() ? 'none' : '';
      item.style.color = ended(motions[i], frame) ? '#9a9a9a' : '';
      item.title = ended(motions[i], frame) ? 'ended: holds its last pose' : '';
    });
  }
  applyLayout(layoutSel.value);
  // follow by default side by side (each cell frames its figure), and in one scene when the motions cover much
  // more ground than a body (long walks); ?follow=0/1 decides
  followBox.checked = q.get('follow') === '1' || (q.get('follow') !== '0' && (layoutSel.value === 'grid' ||
      Math.max(box[1][0] - box[0][0], box[1][2] - box[0][2]) > 4 * hMax));
  resetCamera();
  setPlaying(q.get('paused') !== '1');
  if (q.get('t') !== null) seek(Math.round(num('t', 0) * fpsMaster));       // ?t=SECONDS, every clip at that time
  else seek(Math.round(num('frame', 0) / motions[0].fps * fpsMaster));     // ?frame=N: the first motion's frame N
  function screenOf(mi, j) {  // where joint j of motion mi is drawn (CSS px), in its cell in small multiples
    var m = motions[mi], keep = {eye: view.eye, f: view.f, r: view.r, u: view.u, fpx: view.fpx}, W0 = W, H0 = H;
    var cv = cellMode() ? cellView[mi] : null;
    if (cv) { view.eye = cv.eye; view.f = cv.f; view.r = cv.r; view.u = cv.u; view.fpx = cv.fpx; W = cv.W; H = cv.H; }
    var s = project(toCam(joint(m, frameOf(m, frame), j)));
    if (cv) s = [s[0] + cv.ox, s[1] + cv.oy];
    view.eye = keep.eye; view.f = keep.f; view.r = keep.r; view.u = keep.u; view.fpx = keep.fpx; W = W0; H = H0;
    return [s[0], s[1]];
  }
  var probe = q.get('probe');  // "M,J": pick at joint J of motion M, as the mouse would (a test hook)
  if (probe) {
    var mj = probe.split(',').map(Number), s = screenOf(mj[0], mj[1]), hit = pick(s[0], s[1]);
    document.body.setAttribute('data-probe', hit ? motions[hit.m].names[hit.j] : '');
  }
  window.modiViewer = {  // for scripts and tests: the viewer's state, and where a joint is drawn (CSS px)
    state: function () {
      return {frame: frame, frames: nFrames, playing: playing, speed: speed, az: cam.az, el: cam.el,
              dist: cam.dist, follow: followBox.checked, layout: layoutSel.value, t: frame / fpsMaster,
              frame0: frameOf(motions[0], frame), cells: cellMode() ? [cells.cols, cells.rows] : null,
              ended: motions.map(function (m) { return ended(m, frame); })};
    },
    screenOf: screenOf,
    cellsBox: function () {  // per motion in small multiples: [x, y, w, h] of its cell (CSS px)
      if (!cellMode()) return null;
      return motions.map(function (m, mi) { var c = cellView[mi]; return [c.ox, c.oy, c.W, c.H]; });
    }
  };
  document.body.setAttribute('data-status', 'ready');
  window.requestAnimationFrame(tick);
})();
