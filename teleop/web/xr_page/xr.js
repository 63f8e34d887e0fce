// The XR page: draws the session's scene with WebGL2 (its own small renderer) in a WebXR session, and sends the
// headset's controllers and hands to the server (teleop/web/xr_page/xr_messages.py). The scene arrives once, then
// every control tick the bodies' poses (teleop/web/xr_page/scene_message.py); the page draws at the headset's frame
// rate whatever the server does. Frames: MuJoCo's world (z up, m) is mapped into WebXR's local-floor (y up, -z
// forward) by `place`, set at Enter VR and on recentre so that the operator stands where the scene says
// (placement) with the table top HEADSET_ABOVE below the headset; poses sent back go through its inverse.
(() => {
  'use strict';
  const FORCE_CLIP_N = /*FORCE_CLIP_N*/20;
  const FORCE_MIN_N = 0.5; // below this the fingers are taken as touching nothing
  const IK_LIMIT_M = 0.02; // an arm's IK error above this: its target is out of reach (a pulse marks it)
  const PULSE_MS = 60;
  const RESEND_MS = 100; // an unchanged pose is sent again this often (the server lets go after 250 ms without one)
  const PINCH_ON_M = 0.02, PINCH_OFF_M = 0.035; // a hand's middle-thumb pinch: the clutch
  const GRIP_CLOSE_M = 0.03, GRIP_OPEN_M = 0.05; // a hand's thumb-index gap: the gripper, with hysteresis
  const params = new URLSearchParams(location.search);
  const xr = {
    scene: null, poses: null, forces: [], errors: [], appliedFrame: -1, status: {}, frame: 0, session: null, mode: null,
    placed: false, place: null, placeInv: null, posesReceived: 0, scenesReceived: 0, frameMs: [], frameGapMs: [], lastFrameAt: 0, latencyMs: [],
    measure: false, pulses: [], sent: 0, visible: 'visible', drawnFrames: 0, scale: 1,
  };
  window.__xr = xr; // the tests and the bench read the page's state here

  // ---- small math: column-major 4x4 (WebGL's), quaternions wxyz (MuJoCo's) ----
  const mul = (a, b) => {
    const o = new Float32Array(16);
    for (let c = 0; c < 4; c++) for (let r = 0; r < 4; r++) {
      o[c * 4 + r] = a[r] * b[c * 4] + a[4 + r] * b[c * 4 + 1] + a[8 + r] * b[c * 4 + 2] + a[12 + r] * b[c * 4 + 3];
    }
    return o;
  };
  const poseMat = (p, q, s) => { // translation p, rotation q (wxyz), then scale s (x, y, z)
    const [w, x, y, z] = q; const sx = s ? s[0] : 1, sy = s ? s[1] : 1, sz = s ? s[2] : 1;
    return new Float32Array([
      (1 - 2 * (y * y + z * z)) * sx, 2 * (x * y + w * z) * sx, 2 * (x * z - w * y) * sx, 0,
      2 * (x * y - w * z) * sy, (1 - 2 * (x * x + z * z)) * sy, 2 * (y * z + w * x) * sy, 0,
      2 * (x * z + w * y) * sz, 2 * (y * z - w * x) * sz, (1 - 2 * (x * x + y * y)) * sz, 0,
      p[0], p[1], p[2], 1]);
  };
  const matQuat = (m) => { // rotation part of a rigid 4x4 -> wxyz
    const m00 = m[0], m11 = m[5], m22 = m[10], tr = m00 + m11 + m22;
    let w, x, y, z;
    if (tr > 0) { const s = Math.sqrt(tr + 1) * 2; w = s / 4; x = (m[6] - m[9]) / s; y = (m[8] - m[2]) / s; z = (m[1] - m[4]) / s; }
    else if (m00 > m11 && m00 > m22) { const s = Math.sqrt(1 + m00 - m11 - m22) * 2; w = (m[6] - m[9]) / s; x = s / 4; y = (m[4] + m[1]) / s; z = (m[8] + m[2]) / s; }
    else if (m11 > m22) { const s = Math.sqrt(1 + m11 - m00 - m22) * 2; w = (m[8] - m[2]) / s; x = (m[4] + m[1]) / s; y = s / 4; z = (m[9] + m[6]) / s; }
    else { const s = Math.sqrt(1 + m22 - m00 - m11) * 2; w = (m[1] - m[4]) / s; x = (m[8] + m[2]) / s; y = (m[9] + m[6]) / s; z = s / 4; }
    return [w, x, y, z];
  };
  const rigidInverse = (m) => {
    const o = new Float32Array(16);
    for (let r = 0; r < 3; r++) for (let c = 0; c < 3; c++) o[c * 4 + r] = m[r * 4 + c];
    for (let r = 0; r < 3; r++) o[12 + r] = -(o[r] * m[12] + o[4 + r] * m[13] + o[8 + r] * m[14]);
    o[15] = 1;
    return o;
  };
  const perspective = (fovy, aspect, near, far) => {
    const f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0]);
  };
  const lookAt = (eye, at, up) => {
    const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
    const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]];
    const norm = (a) => { const l = Math.hypot(...a) || 1; return [a[0] / l, a[1] / l, a[2] / l]; };
    const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
    const z = norm(sub(eye, at)), x = norm(cross(up, z)), y = cross(z, x);
    return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0, -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
  };

  // ---- the placement: MuJoCo world -> local-floor, from the headset's pose at Enter VR / recentre ----
  function placeFrom(head) { // head: XRRigidTransform of the viewer in local-floor
    const p = xr.scene.placement, o = head.orientation;
    const q = [o.w, o.x, o.y, o.z], hm = poseMat([0, 0, 0], q);
    let fx = -hm[8], fz = -hm[10]; // where the headset looks (-z), flattened
    const l = Math.hypot(fx, fz) || 1; fx /= l; fz /= l;
    const F = [fx, 0, fz], L = [fz, 0, -fx], c = Math.cos(p.yaw), s = Math.sin(p.yaw);
    const col0 = [c * F[0] - s * L[0], 0, c * F[2] - s * L[2]];
    const col1 = [s * F[0] + c * L[0], 0, s * F[2] + c * L[2]];
    const H = [head.position.x, head.position.y - p.headset_above_m, head.position.z], S = p.stand;
    const t = [0, 1, 2].map((i) => H[i] - (col0[i] * S[0] + col1[i] * S[1] + (i === 1 ? 1 : 0) * S[2]));
    xr.place = new Float32Array([...col0, 0, ...col1, 0, 0, 1, 0, 0, ...t, 1]);
    xr.placeInv = rigidInverse(xr.place);
    xr.placed = true;
  }

  // ---- the renderer ----
  const canvas = document.getElementById('view');
  const gl = canvas.getContext('webgl2', { xrCompatible: true, antialias: false, alpha: true });
  const compile = (type, src) => {
    const sh = gl.createShader(type); gl.shaderSource(sh, src); gl.compileShader(sh);
    if (!gl.getShaderParameter(sh, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(sh));
    return sh;
  };
  const program = (vs, fs) => {
    const p = gl.createProgram();
    gl.attachShader(p, compile(gl.VERTEX_SHADER, vs)); gl.attachShader(p, compile(gl.FRAGMENT_SHADER, fs));
    gl.bindAttribLocation(p, 0, 'aPos'); gl.linkProgram(p);
    return p;
  };
  // Flat shading from the surface's own slope (screen-space derivatives): no normals to send or compute.
  const solid = program(`#version 300 es
    in vec3 aPos; uniform mat4 uModel, uViewProj; out vec3 vWorld;
    void main() { vec4 w = uModel * vec4(aPos, 1.0); vWorld = w.xyz; gl_Position = uViewProj * w; }`, `#version 300 es
    precision highp float; in vec3 vWorld; uniform vec4 uColor; out vec4 outColor;
    void main() {
      vec3 n = normalize(cross(dFdx(vWorld), dFdy(vWorld)));
      float key = abs(dot(n, normalize(vec3(0.35, 0.25, 1.0)))), fill = abs(dot(n, normalize(vec3(-0.6, 0.5, 0.3))));
      outColor = vec4(uColor.rgb * (0.3 + 0.55 * key + 0.25 * fill), uColor.a);
    }`);
  const textured = program(`#version 300 es
    in vec3 aPos; uniform mat4 uModel, uViewProj; out vec2 vUv;
    void main() { vUv = vec2(aPos.x * 0.5 + 0.5, 0.5 - aPos.y * 0.5); gl_Position = uViewProj * uModel * vec4(aPos, 1.0); }`, `#version 300 es
    precision highp float; in vec2 vUv; uniform sampler2D uTex; out vec4 outColor;
    void main() { outColor = texture(uTex, vUv); }`);
  const loc = (p, n) => gl.getUniformLocation(p, n);
  const U = { model: loc(solid, 'uModel'), viewProj: loc(solid, 'uViewProj'), color: loc(solid, 'uColor'),
    tModel: loc(textured, 'uModel'), tViewProj: loc(textured, 'uViewProj'), tTex: loc(textured, 'uTex') };

  const shape = (positions, indices) => {
    const vao = gl.createVertexArray(); gl.bindVertexArray(vao);
    const vb = gl.createBuffer(); gl.bindBuffer(gl.ARRAY_BUFFER, vb);
    gl.bufferData(gl.ARRAY_BUFFER, positions, gl.STATIC_DRAW);
    gl.enableVertexAttribArray(0); gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    const ib = gl.createBuffer(); gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, ib);
    gl.bufferData(gl.ELEMENT_ARRAY_BUFFER, indices, gl.STATIC_DRAW);
    gl.bindVertexArray(null);
    return { vao, count: indices.length };
  };
  const box = () => { // [-1, 1]^3
    const p = [], idx = [];
    const faces = [[0, 1, 2], [1, 2, 0], [2, 0, 1]];
    for (const [a, b, c] of faces) for (const sgn of [1, -1]) {
      const base = p.length / 3;
      for (const [u, v] of [[-1, -1], [1, -1], [1, 1], [-1, 1]]) { const q = [0, 0, 0]; q[a] = sgn; q[b] = u; q[c] = v; p.push(...q); }
      idx.push(base, base + 1, base + 2, base, base + 2, base + 3);
    }
    return shape(new Float32Array(p), new Uint32Array(idx));
  };
  const sphere = (rings = 12, segs = 18) => { // unit radius
    const p = [], idx = [];
    for (let i = 0; i <= rings; i++) {
      const th = Math.PI * i / rings;
      for (let j = 0; j <= segs; j++) { const ph = 2 * Math.PI * j / segs; p.push(Math.sin(th) * Math.cos(ph), Math.sin(th) * Math.sin(ph), Math.cos(th)); }
    }
    for (let i = 0; i < rings; i++) for (let j = 0; j < segs; j++) {
      const a = i * (segs + 1) + j, b = a + segs + 1;
      idx.push(a, b, a + 1, a + 1, b, b + 1);
    }
    return shape(new Float32Array(p), new Uint32Array(idx));
  };
  const cylinder = (segs = 20) => { // radius 1, z in [-1, 1], capped
    const p = [0, 0, 1, 0, 0, -1], idx = [];
    for (let j = 0; j <= segs; j++) { const ph = 2 * Math.PI * j / segs; p.push(Math.cos(ph), Math.sin(ph), 1, Math.cos(ph), Math.sin(ph), -1); }
    for (let j = 0; j < segs; j++) {
      const t0 = 2 + 2 * j, b0 = t0 + 1, t1 = t0 + 2, b1 = t0 + 3;
      idx.push(t0, b0, t1, t1, b0, b1, 0, t0, t1, 1, b1, b0);
    }
    return shape(new Float32Array(p), new Uint32Array(idx));
  };
  const quad = () => shape(new Float32Array([-1, -1, 0, 1, -1, 0, 1, 1, 0, -1, 1, 0]), new Uint32Array([0, 1, 2, 0, 2, 3]));
  const SHAPES = { box: box(), sphere: sphere(), cylinder: cylinder(), plane: quad() };

  // The scene message -> a draw list: per geom, its body, colour and parts (shape, matrix in the body's frame).
  function loadScene(buffer) {
    const view = new DataView(buffer), length = view.getUint32(4, true);
    const head = JSON.parse(new TextDecoder().decode(new Uint8Array(buffer, 8, length)));
    const data = 8 + length, meshes = {};
    for (const [id, m] of Object.entries(head.meshes)) {
      meshes[id] = shape(new Float32Array(buffer.slice(data + m.vert, data + m.vert + m.nvert * 12)),
        new Uint32Array(buffer.slice(data + m.face, data + m.face + m.nface * 12)));
    }
    const draws = head.geoms.map((g) => {
      const local = poseMat(g.pos, g.quat), s = g.size, parts = [];
      if (g.type === 'box') parts.push([SHAPES.box, mul(local, poseMat([0, 0, 0], [1, 0, 0, 0], s))]);
      else if (g.type === 'sphere') parts.push([SHAPES.sphere, mul(local, poseMat([0, 0, 0], [1, 0, 0, 0], [s[0], s[0], s[0]]))]);
      else if (g.type === 'ellipsoid') parts.push([SHAPES.sphere, mul(local, poseMat([0, 0, 0], [1, 0, 0, 0], s))]);
      else if (g.type === 'cylinder' || g.type === 'capsule') {
        parts.push([SHAPES.cylinder, mul(local, poseMat([0, 0, 0], [1, 0, 0, 0], [s[0], s[0], s[1]]))]);
        if (g.type === 'capsule') for (const end of [1, -1]) parts.push([SHAPES.sphere, mul(local, poseMat([0, 0, end * s[1]], [1, 0, 0, 0], [s[0], s[0], s[0]]))]);
      } else if (g.type === 'plane') {
        const hx = s[0] > 0 ? s[0] : 3, hy = s[1] > 0 ? s[1] : 3;
        parts.push([SHAPES.plane, mul(local, poseMat([0, 0, 0], [1, 0, 0, 0], [hx, hy, 1]))]);
      } else if (g.type === 'mesh' && meshes[g.mesh]) parts.push([meshes[g.mesh], local]);
      return { body: g.body, color: g.rgba, parts, plane: g.type === 'plane' };
    });
    xr.scene = { ...head, draws };
    xr.scenesReceived += 1;
    xr.placed = false;
    if (!xr.session) previewDirty = true;
  }

  const bodyMats = [];
  function bodyMatrix(b) {
    const poses = xr.poses;
    if (!poses || b * 7 + 6 >= poses.length) return poseMat([0, 0, 0], [1, 0, 0, 0]);
    const o = b * 7;
    return poseMat([poses[o], poses[o + 1], poses[o + 2]], [poses[o + 3], poses[o + 4], poses[o + 5], poses[o + 6]]);
  }

  // ---- the panel in the scene: the session page's state as text on a quad beside the table ----
  const panelCanvas = document.createElement('canvas'); panelCanvas.width = 512; panelCanvas.height = 256;
  const panelTex = gl.createTexture();
  let panelText = '';
  function panelLines() {
    const s = xr.status || {};
    const lines = [s.recording ? `REC  ${(s.episode_s || 0).toFixed(1)} s` : 'not recording', `seed ${s.seed ?? '-'}`,
      s.success ? 'success' : 'task not done yet', `saved ${s.saved ?? 0}`];
    if (s.lost && s.lost.length) lines.push(`lost: ${s.lost.join(', ')}`);
    return lines.join('\n');
  }
  function updatePanel() {
    const text = panelLines();
    if (text === panelText) return;
    panelText = text;
    const c = panelCanvas.getContext('2d');
    c.fillStyle = 'rgba(25, 28, 34, 0.9)'; c.fillRect(0, 0, 512, 256);
    c.fillStyle = '#f2f2f2'; c.font = '34px sans-serif';
    text.split('\n').forEach((line, i) => { c.fillStyle = i === 0 && xr.status.recording ? '#ff6060' : '#f2f2f2'; c.fillText(line, 20, 50 + i * 46); });
    gl.bindTexture(gl.TEXTURE_2D, panelTex);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, gl.RGBA, gl.UNSIGNED_BYTE, panelCanvas);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
  }
  function panelMatrix() { // 0.3 x 0.15 m, upright, ahead-left of the operator, facing them
    const p = xr.scene.placement, c = Math.cos(p.yaw), s = Math.sin(p.yaw);
    const at = [p.stand[0] + 0.9 * c - 0.35 * s, p.stand[1] + 0.9 * s + 0.35 * c, p.stand[2] + 0.3];
    // quad x -> the operator's right, quad y -> up, facing back at them
    return new Float32Array([0.15 * s, -0.15 * c, 0, 0, 0, 0, 0.075, 0, -c, -s, 0, 0, at[0], at[1], at[2], 1]);
  }

  function drawScene(viewProj, ar) {
    if (!xr.scene) return;
    gl.enable(gl.DEPTH_TEST); gl.disable(gl.CULL_FACE);
    gl.useProgram(solid);
    gl.uniformMatrix4fv(U.viewProj, false, viewProj);
    const nb = xr.scene.bodies;
    for (let b = 0; b < nb; b++) bodyMats[b] = bodyMatrix(b);
    for (const pass of [false, true]) { // opaque, then translucent
      if (pass) { gl.enable(gl.BLEND); gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA); gl.depthMask(false); }
      for (const d of xr.scene.draws) {
        if ((d.color[3] < 1) !== pass || (ar && d.plane)) continue;
        gl.uniform4fv(U.color, d.color);
        for (const [sh, local] of d.parts) {
          gl.uniformMatrix4fv(U.model, false, mul(bodyMats[d.body], local));
          gl.bindVertexArray(sh.vao); gl.drawElements(gl.TRIANGLES, sh.count, gl.UNSIGNED_INT, 0);
        }
      }
      gl.disable(gl.BLEND); gl.depthMask(true);
    }
    updatePanel();
    gl.useProgram(textured);
    gl.uniformMatrix4fv(U.tViewProj, false, viewProj);
    gl.uniformMatrix4fv(U.tModel, false, panelMatrix());
    gl.activeTexture(gl.TEXTURE0); gl.bindTexture(gl.TEXTURE_2D, panelTex); gl.uniform1i(U.tTex, 0);
    gl.bindVertexArray(SHAPES.plane.vao); gl.drawElements(gl.TRIANGLES, SHAPES.plane.count, gl.UNSIGNED_INT, 0);
    gl.bindVertexArray(null);
  }

  // ---- the page's own view (before Enter VR): a fixed camera behind the operator's place ----
  let previewDirty = true, previewDue = 0;
  function preview(now) {
    if (!xr.session) {
      if (previewDirty && xr.scene && now >= previewDue) {
        previewDirty = false; previewDue = now + 100;
        const w = canvas.clientWidth, h = canvas.clientHeight;
        if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; }
        gl.bindFramebuffer(gl.FRAMEBUFFER, null); gl.viewport(0, 0, w, h);
        gl.clearColor(0.11, 0.13, 0.15, 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
        const p = xr.scene.placement, c = Math.cos(p.yaw), s = Math.sin(p.yaw);
        const eye = [p.stand[0] - 0.5 * c, p.stand[1] - 0.5 * s, p.stand[2] + 0.7];
        const at = [p.stand[0] + 0.5 * c, p.stand[1] + 0.5 * s, p.stand[2]];
        drawScene(mul(perspective(1.0, w / Math.max(h, 1), 0.02, 30), lookAt(eye, at, [0, 0, 1])), false);
      }
      requestAnimationFrame(preview);
    }
  }

  // ---- the server ----
  let ws = null;
  const send = (m) => { if (ws && ws.readyState === 1) { ws.send(JSON.stringify(m)); xr.sent += 1; } };
  function connect() {
    const proto = location.protocol === 'https:' ? 'wss:' : 'ws:';
    const token = params.get('token');
    ws = new WebSocket(`${proto}//${location.host}/teleop/xr${token ? `?token=${encodeURIComponent(token)}` : ''}`);
    ws.binaryType = 'arraybuffer';
    ws.onopen = () => { send({ type: 'xr_config', scale: xr.scale }); showStatus(); };
    ws.onmessage = (event) => {
      if (typeof event.data === 'string') {
        const m = JSON.parse(event.data);
        if (m.type === 'status') { xr.status = m; showStatus(); }
        return;
      }
      const magic = new TextDecoder().decode(new Uint8Array(event.data, 0, 4));
      if (magic === 'TXR1') loadScene(event.data);
      else if (magic === 'TXP1') {
        const v = new DataView(event.data), n = v.getUint32(8, true), arms = v.getUint32(12, true);
        xr.poses = new Float32Array(event.data, 32, n * 7);
        xr.forces = Array.from(new Float32Array(event.data, 32 + n * 28, arms));
        xr.errors = Array.from(new Float32Array(event.data, 32 + n * 28 + arms * 4, arms));
        const applied = v.getFloat64(24, true);
        if (applied > xr.appliedFrame) {
          const stamp = sentAt.get(applied);
          if (stamp !== undefined) { xr.latencyMs.push(performance.now() - stamp); sentAt.delete(applied); }
          xr.appliedFrame = applied;
        }
        xr.posesReceived += 1;
        previewDirty = true;
      }
    };
    ws.onclose = () => { showStatus('disconnected from the server: reconnecting...'); setTimeout(connect, 1000); };
  }
  const sentAt = new Map(); // frame number -> when its changed pose was sent (the latency figure)

  function showStatus(extra) {
    const s = xr.status || {};
    document.getElementById('status').textContent = extra || [
      ws && ws.readyState === 1 ? 'connected' : 'connecting...', s.recording ? `recording ${(s.episode_s || 0).toFixed(1)} s` : '',
      s.seed !== undefined ? `seed ${s.seed}` : ''].filter(Boolean).join('  ');
  }

  // ---- input: controllers and hands -> xr_pose / xr_button ----
  const hands = { left: { last: null, lastAt: 0, buttons: [], pinch: false, grip: 1, squeeze: false, pulseAt: 0 },
    right: { last: null, lastAt: 0, buttons: [], pinch: false, grip: 1, squeeze: false, pulseAt: 0 } };
  xr.hands = hands;
  const worldPose = (m) => { // an XR pose matrix (local-floor) -> [pos, quat wxyz] in the world frame
    const w = mul(xr.placeInv, m);
    return [[w[12], w[13], w[14]], matQuat(w)];
  };
  const dist = (a, b) => Math.hypot(a.x - b.x, a.y - b.y, a.z - b.z);
  function pulse(source, intensity, ms) {
    const pad = source && source.gamepad;
    const actuator = pad && pad.hapticActuators && pad.hapticActuators[0];
    if (actuator && actuator.pulse) { actuator.pulse(Math.min(1, Math.max(0, intensity)), ms); xr.pulses.push(intensity); }
  }
  function readInputs(frame, ref, now) {
    const seen = new Set();
    for (const source of frame.session.inputSources) {
      const side = source.handedness;
      if (side !== 'left' && side !== 'right') continue;
      const h = hands[side];
      seen.add(side);
      let pose = null, clutch = false, opening = null, mode = 'controller';
      if (source.hand) {
        mode = 'hand';
        const joint = (name) => { const j = source.hand.get(name); const p = j && frame.getJointPose(j, ref); return p && p.transform.position; };
        const wrist = source.hand.get('wrist'), wp = wrist && frame.getJointPose(wrist, ref);
        pose = wp ? wp.transform.matrix : null;
        const thumb = joint('thumb-tip'), index = joint('index-finger-tip'), middle = joint('middle-finger-tip');
        if (thumb && middle) { const d = dist(thumb, middle); h.pinch = h.pinch ? d < PINCH_OFF_M : d < PINCH_ON_M; }
        if (thumb && index) { const d = dist(thumb, index); h.grip = d < GRIP_CLOSE_M ? 0 : d > GRIP_OPEN_M ? 1 : h.grip; }
        clutch = h.pinch; opening = h.grip;
      } else if (source.gripSpace) {
        const p = frame.getPose(source.gripSpace, ref);
        pose = p ? p.transform.matrix : null;
        const pad = source.gamepad;
        if (pad) {
          opening = 1 - (pad.buttons[0] ? pad.buttons[0].value : 0);
          clutch = !!(pad.buttons[1] && pad.buttons[1].value > 0.5);
          const names = side === 'right' ? { 4: 'a', 5: 'b' } : { 4: 'x', 5: 'y' };
          for (const [i, name] of Object.entries(names)) {
            const down = !!(pad.buttons[i] && pad.buttons[i].pressed);
            if (down && !h.buttons[i]) {
              if (name === 'y') xr.placed = false; // recentre
              send({ type: 'xr_button', hand: side, button: name });
            }
            h.buttons[i] = down;
          }
        }
      }
      if (clutch && !h.squeeze) pulse(source, 0.4, 30); // engaged
      h.squeeze = clutch;
      const arm = armOf(side), force = arm === null ? 0 : (xr.forces[arm] || 0);
      if (force > FORCE_MIN_N && now - h.pulseAt >= PULSE_MS) { h.pulseAt = now; pulse(source, force / FORCE_CLIP_N, PULSE_MS); }
      const limited = arm !== null && (xr.errors[arm] || 0) > IK_LIMIT_M; // the target out of the arm's reach: one pulse as it starts
      if (limited && !h.limited && h.squeeze) pulse(source, 0.8, 40);
      h.limited = limited;
      let message;
      if (pose) {
        const [pos, quat] = worldPose(pose);
        message = { type: 'xr_pose', hand: side, frame: xr.frame, t: xr.frameEpochMs, tracked: true, pos: pos.map(clean), quat: quat.map(clean), clutch, opening, mode };
      } else message = { type: 'xr_pose', hand: side, frame: xr.frame, t: xr.frameEpochMs, tracked: false, pos: null, quat: null, clutch: false, opening, mode };
      sendPose(h, message, now);
    }
    for (const side of ['left', 'right']) {
      const h = hands[side];
      if (!seen.has(side) && h.last && h.last.tracked) { // the source went away (tracking lost, controller off)
        sendPose(h, { type: 'xr_pose', hand: side, frame: xr.frame, t: xr.frameEpochMs, tracked: false, pos: null, quat: null, clutch: false, opening: null, mode: h.last.mode }, now);
      }
    }
  }
  const clean = (v) => (Number.isFinite(v) ? Math.round(v * 1e6) / 1e6 : null); // a NaN goes as null: the server counts it
  function sendPose(h, message, now) {
    const key = JSON.stringify({ ...message, frame: 0, t: 0 });
    if (h.lastKey === key && now - h.lastAt < RESEND_MS) return;
    if (h.lastKey !== key) sentAt.set(message.frame, now);
    if (sentAt.size > 500) sentAt.delete(sentAt.keys().next().value);
    h.lastKey = key; h.last = message; h.lastAt = now;
    send(message);
  }
  const armOf = (side) => ((xr.scene && xr.scene.arms >= 2) ? (side === 'left' ? 0 : 1) : (side === 'right' ? 0 : null));

  // ---- the XR session ----
  function onFrame(time, frame) {
    const session = frame.session;
    session.requestAnimationFrame(onFrame);
    xr.frame += 1;
    const start = performance.now();
    if (xr.lastFrameAt) xr.frameGapMs.push(start - xr.lastFrameAt);
    if (xr.frameGapMs.length > 600) xr.frameGapMs.shift();
    xr.lastFrameAt = start;
    xr.frameEpochMs = Math.round((performance.timeOrigin + start) * 10) / 10;
    const pose = frame.getViewerPose(xr.ref);
    if (!pose || !xr.scene) return;
    if (!xr.placed) placeFrom(pose.transform);
    if (session.visibilityState === 'visible') readInputs(frame, xr.ref, start);
    const layer = session.renderState.baseLayer;
    gl.bindFramebuffer(gl.FRAMEBUFFER, layer.framebuffer);
    const ar = xr.mode === 'immersive-ar';
    gl.clearColor(0.11, 0.13, 0.15, ar ? 0 : 1); gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
    for (const view of pose.views) {
      const vp = layer.getViewport(view);
      gl.viewport(vp.x, vp.y, vp.width, vp.height);
      drawScene(mul(mul(view.projectionMatrix, view.transform.inverse.matrix), xr.place), ar);
    }
    if (xr.measure) gl.finish();
    xr.frameMs.push(performance.now() - start);
    if (xr.frameMs.length > 600) xr.frameMs.shift();
    xr.drawnFrames += 1;
  }
  async function enter(mode) {
    if (xr.session) return;
    const session = await navigator.xr.requestSession(mode, { requiredFeatures: ['local-floor'], optionalFeatures: ['hand-tracking'] });
    await gl.makeXRCompatible();
    session.updateRenderState({ baseLayer: new XRWebGLLayer(session, gl) });
    xr.ref = await session.requestReferenceSpace('local-floor');
    xr.session = session; xr.mode = mode; xr.placed = false; xr.visible = session.visibilityState;
    session.addEventListener('visibilitychange', () => {
      xr.visible = session.visibilityState;
      if (session.visibilityState !== 'visible') send({ type: 'xr_release', why: session.visibilityState === 'hidden' ? 'hidden' : 'blurred' });
    });
    session.addEventListener('end', () => {
      send({ type: 'xr_release', why: 'ended' });
      xr.session = null; previewDirty = true; requestAnimationFrame(preview);
    });
    session.requestAnimationFrame(onFrame);
  }
  window.addEventListener('pagehide', () => send({ type: 'xr_release', why: 'pagehide' }));

  // ---- the page's controls ----
  const vr = document.getElementById('enter-vr'), arButton = document.getElementById('enter-ar');
  vr.addEventListener('click', () => enter('immersive-vr').catch((e) => showStatus(`Enter VR failed: ${e.message}`)));
  arButton.addEventListener('click', () => enter('immersive-ar').catch((e) => showStatus(`Enter AR failed: ${e.message}`)));
  document.getElementById('recentre').addEventListener('click', () => { xr.placed = false; });
  const slider = document.getElementById('scale'), scaleText = document.getElementById('scale-text');
  const setScale = (v) => {
    xr.scale = Math.min(3, Math.max(0.25, v)); slider.value = String(xr.scale); scaleText.textContent = xr.scale.toFixed(2);
    send({ type: 'xr_config', scale: xr.scale });
  };
  slider.addEventListener('input', () => setScale(parseFloat(slider.value)));
  if (params.get('scale') && Number.isFinite(parseFloat(params.get('scale')))) setScale(parseFloat(params.get('scale')));
  document.getElementById('session-link').href = `/${params.get('token') ? `?token=${encodeURIComponent(params.get('token'))}` : ''}`;
  if (navigator.xr) {
    navigator.xr.isSessionSupported('immersive-vr').then((ok) => { vr.disabled = !ok; if (!ok) vr.title = 'this browser has no immersive-vr'; });
    navigator.xr.isSessionSupported('immersive-ar').then((ok) => { arButton.hidden = !ok; }).catch(() => {});
  } else vr.title = 'WebXR needs a secure context (https, or http://localhost)';
  connect();
  requestAnimationFrame(preview);
})();
