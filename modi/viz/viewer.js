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
            J: m.names.length, pos: pos, con: con, off: [0, 0, 0], color: D.colors[m.color % D.colors.length]};
  });
  var fpsMaster = Math.max.apply(null, motions.map(function (m) { return m.fps; }));
  var nFrames = 1 + Math.round(Math.max.apply(null, motions.map(function (m) {
    return (m.T - 1) / m.fps; })) * fpsMaster);
  var hMax = Math.max.apply(null, D.motions.map(function (m) { return m.height; }));

  function frameOf(m, f) { return Math.min(m.T - 1, Math.round(f / fpsMaster * m.fps)); }
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
  });
  function applyLayout(kind) {
    var n = motions.length, cols = Math.ceil(Math.sqrt(n)), sp = hMax;
    motions.forEach(function (m) {
      sp = Math.max(sp, 1.15 * (m.bounds[1][0] - m.bounds[0][0]), 1.15 * (m.bounds[1][2] - m.bounds[0][2]));
    });
    motions.forEach(function (m, i) {
      if (kind === 'scene' || n === 1) { m.off = [0, 0, 0]; return; }
      var b = m.bounds, r = Math.floor(i / cols), c = i % cols;
      m.off = [c * sp - (b[0][0] + b[1][0]) / 2, 0, r * sp - (b[0][2] + b[1][2]) / 2];
    });
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
  function draw() {
    var dpr = window.devicePixelRatio || 1;
    W = stage.clientWidth; H = stage.clientHeight;
    if (canvas.width !== Math.round(W * dpr) || canvas.height !== Math.round(H * dpr)) {
      canvas.width = Math.round(W * dpr); canvas.height = Math.round(H * dpr);
    }
    ctx.setTransform(dpr, 0, 0, dpr, 0, 0);
    ctx.fillStyle = D.style.background; ctx.fillRect(0, 0, W, H);
    var target = cam.target;
    if (followBox.checked) {  // the group's centre, shifted by any pan since the reset
      var g = groupCentre(frame);
      target = [g[0] + cam.target[0] - cam.home[0], cam.target[1], g[1] + cam.target[2] - cam.home[2]];
    }
    setupView(target);
    drawGrid();
    var bones = [];
    drawn = [];
    motions.forEach(function (m, mi) {
      var t = frameOf(m, frame), P = [];
      for (var j = 0; j < m.J; j++) P.push(joint(m, t, j));
      for (j = 0; j < m.J; j++) {  // floor shadow first: it lies under everything
        var p = m.parents[j];
        if (p >= 0 && !m.hide[j]) line([P[p][0], 0, P[p][2]], [P[j][0], 0, P[j][2]], D.style.shadow, 3);
      }
      for (j = 0; j < m.J; j++) {
        var c = toCam(P[j]);
        var on = m.con ? m.con[t * m.J + j] === 1 : false;
        if (on) ring(P[j], 0.04 * hMax, D.style.contactRing);
        if (c[2] > NEAR && !m.marker[j]) drawn.push({m: mi, j: j, s: project(c), on: on, depth: c[2]});
        p = m.parents[j];
        if (p >= 0 && !m.hide[j]) bones.push({a: P[p], b: P[j], color: m.color[m.side[j]], depth: (toCam(P[p])[2] + c[2]) / 2});
      }
    });
    bones.sort(function (a, b) { return b.depth - a.depth; });
    bones.forEach(function (b) {
      line(b.a, b.b, b.color, Math.max(1.5, Math.min(9, 0.035 * hMax * view.fpx / Math.max(b.depth, NEAR))));
    });
    drawn.forEach(function (d) {
      var m = motions[d.m], r = Math.max(1.5, Math.min(7, 0.02 * hMax * view.fpx / d.depth)) * (d.on ? 1.8 : 1);
      ctx.fillStyle = d.on ? D.style.contact : m.color[m.side[d.j]];
      ctx.beginPath(); ctx.arc(d.s[0], d.s[1], r, 0, 2 * Math.PI); ctx.fill();
    });
    if (layoutSel.value === 'grid' && motions.length > 1) {
      ctx.fillStyle = D.style.text; ctx.font = '12px sans-serif'; ctx.textAlign = 'center';
      motions.forEach(function (m) {
        var b = m.bounds, c = toCam([(b[0][0] + b[1][0]) / 2 + m.off[0], 1.12 * b[1][1],
                                     (b[0][2] + b[1][2]) / 2 + m.off[2]]);
        if (c[2] > NEAR) { var s = project(c); ctx.fillText(m.title, s[0], s[1]); }
      });
    }
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
    frameLabel.textContent = 'frame ' + frame + ' / ' + (nFrames - 1) + ' \u00b7 ' + (frame / fpsMaster).toFixed(2) + ' s';
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
  followBox.addEventListener('change', function () { fitDistance(); draw(); });
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
  motions.forEach(function (m) {
    var item = document.createElement('span'), sw = document.createElement('i');
    sw.style.background = m.color[0]; item.appendChild(sw);
    item.appendChild(document.createTextNode(m.title));
    legend.appendChild(item);
  });
  applyLayout(layoutSel.value);
  // follow by default when the motions cover much more ground than a body (long walks); ?follow=0/1 decides
  followBox.checked = q.get('follow') === '1' || (q.get('follow') !== '0' &&
      Math.max(box[1][0] - box[0][0], box[1][2] - box[0][2]) > 4 * hMax);
  resetCamera();
  setPlaying(q.get('paused') !== '1');
  seek(num('frame', 0));
  var probe = q.get('probe');  // "M,J": pick at joint J of motion M, as the mouse would (a test hook)
  if (probe) {
    var mj = probe.split(',').map(Number), m0 = motions[mj[0]];
    var s = project(toCam(joint(m0, frameOf(m0, frame), mj[1]))), hit = pick(s[0], s[1]);
    document.body.setAttribute('data-probe', hit ? motions[hit.m].names[hit.j] : '');
  }
  window.modiViewer = {  // for scripts and tests: the viewer's state, and where a joint is drawn (CSS px)
    state: function () {
      return {frame: frame, frames: nFrames, playing: playing, speed: speed, az: cam.az, el: cam.el,
              dist: cam.dist, follow: followBox.checked, layout: layoutSel.value};
    },
    screenOf: function (mi, j) {
      var m = motions[mi], s = project(toCam(joint(m, frameOf(m, frame), j)));
      return [s[0], s[1]];
    }
  };
  document.body.setAttribute('data-status', 'ready');
  window.requestAnimationFrame(tick);
})();
