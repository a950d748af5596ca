// scope3d report viewer: a small WebGL 1 viewer of our own (no library, no network).
// Reads the JSON in <script id="scene-data">: layers (positions float32, faces uint32, colours RGB bytes
// per colouring, all base64), camera frusta (line segments), trajectory, fluorescent targets, up axis.
// Mouse: drag = orbit, shift-drag or right-drag = pan, wheel = zoom, click = the explorer: the frames that
// saw the clicked spot (projected with each frame's pose and intrinsics, inside the image and facing the
// camera), listed beside the view with the spot circled on their pictures. A closed cavity (the organ
// panorama) is seen from inside, like a virtual globe. State for tests: body[data-viewer], body[data-picked], body[data-explore-ms]
// (the click's time), body[data-textures-loaded].
(function () {
  "use strict";

  function decode(b64, Type) {
    if (!b64) return null;
    var bin = atob(b64);
    var bytes = new Uint8Array(bin.length);
    for (var i = 0; i < bin.length; i++) bytes[i] = bin.charCodeAt(i);
    return new Type(bytes.buffer);
  }

  // --- 4x4 matrices, column-major as WebGL wants them ---
  function perspective(fovy, aspect, near, far) {
    var f = 1 / Math.tan(fovy / 2), nf = 1 / (near - far);
    return [f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1, 0, 0, 2 * far * near * nf, 0];
  }
  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function add(a, b) { return [a[0] + b[0], a[1] + b[1], a[2] + b[2]]; }
  function scale(a, s) { return [a[0] * s, a[1] * s, a[2] * s]; }
  function dot(a, b) { return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function norm(a) { var n = Math.sqrt(dot(a, a)) || 1; return [a[0] / n, a[1] / n, a[2] / n]; }
  function lookAt(eye, target, up) {
    var z = norm(sub(eye, target)), x = norm(cross(up, z)), y = cross(z, x);
    return [x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
            -dot(x, eye), -dot(y, eye), -dot(z, eye), 1];
  }
  function multiply(a, b) {
    var out = new Array(16);
    for (var c = 0; c < 4; c++) for (var r = 0; r < 4; r++) {
      var s = 0;
      for (var k = 0; k < 4; k++) s += a[k * 4 + r] * b[c * 4 + k];
      out[c * 4 + r] = s;
    }
    return out;
  }
  function project(m, p) {
    var x = m[0] * p[0] + m[4] * p[1] + m[8] * p[2] + m[12];
    var y = m[1] * p[0] + m[5] * p[1] + m[9] * p[2] + m[13];
    var w = m[3] * p[0] + m[7] * p[1] + m[11] * p[2] + m[15];
    return w > 0 ? [x / w, y / w, w] : null;
  }

  var VERTEX = [
    "attribute vec3 position; attribute vec3 colour; attribute vec3 normal; attribute vec2 uv;",
    "uniform mat4 mvp; uniform float pointSize; uniform vec3 eyeDir; uniform float lit;",
    "varying vec3 vColour; varying float vShade; varying vec2 vUv;",
    "void main() {",
    "  gl_Position = mvp * vec4(position, 1.0); gl_PointSize = pointSize;",
    "  vShade = mix(1.0, 0.35 + 0.65 * abs(dot(normalize(normal + vec3(1e-9)), eyeDir)), lit);",
    "  vColour = colour; vUv = uv;",
    "}"].join("\n");
  // highp where the GPU has it: a 2048-texel atlas needs more than mediump's 10-bit texture coordinates
  var FRAGMENT = [
    "#ifdef GL_FRAGMENT_PRECISION_HIGH", "precision highp float;", "#else", "precision mediump float;", "#endif",
    "varying vec3 vColour; varying float vShade; varying vec2 vUv; uniform sampler2D atlas; uniform float textured;",
    "void main() {",
    "  vec3 base = textured > 0.5 ? texture2D(atlas, vUv).rgb : vColour;",
    "  gl_FragColor = vec4(base * vShade, 1.0);",
    "}"].join("\n");

  function compile(gl, type, source) {
    var shader = gl.createShader(type);
    gl.shaderSource(shader, source);
    gl.compileShader(shader);
    if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
    return shader;
  }

  function vertexNormals(pos, faces) {
    var n = new Float32Array(pos.length);
    for (var f = 0; f < faces.length; f += 3) {
      var a = faces[f] * 3, b = faces[f + 1] * 3, c = faces[f + 2] * 3;
      var e1 = [pos[b] - pos[a], pos[b + 1] - pos[a + 1], pos[b + 2] - pos[a + 2]];
      var e2 = [pos[c] - pos[a], pos[c + 1] - pos[a + 1], pos[c + 2] - pos[a + 2]];
      var fn = cross(e1, e2);
      [a, b, c].forEach(function (v) { n[v] += fn[0]; n[v + 1] += fn[1]; n[v + 2] += fn[2]; });
    }
    return n;
  }

  function start() {
    var data = JSON.parse(document.getElementById("scene-data").textContent);
    var canvas = document.getElementById("view");
    var overlay = document.getElementById("view-labels");
    var gl = canvas.getContext("webgl", {antialias: true, preserveDrawingBuffer: true}) ||
             canvas.getContext("experimental-webgl", {preserveDrawingBuffer: true});
    if (!gl) {
      document.body.setAttribute("data-viewer", "no-webgl");
      document.getElementById("view-message").textContent =
        "This browser gives no WebGL context: the 3D view is off (the figures and tables below are complete).";
      return;
    }
    var uintIndices = !!gl.getExtension("OES_element_index_uint");
    var program = gl.createProgram();
    gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, VERTEX));
    gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, FRAGMENT));
    gl.linkProgram(program);
    gl.useProgram(program);
    var loc = {
      position: gl.getAttribLocation(program, "position"), colour: gl.getAttribLocation(program, "colour"),
      normal: gl.getAttribLocation(program, "normal"), mvp: gl.getUniformLocation(program, "mvp"),
      pointSize: gl.getUniformLocation(program, "pointSize"), eyeDir: gl.getUniformLocation(program, "eyeDir"),
      lit: gl.getUniformLocation(program, "lit"), uv: gl.getAttribLocation(program, "uv"),
      textured: gl.getUniformLocation(program, "textured"), atlas: gl.getUniformLocation(program, "atlas")
    };
    gl.uniform1i(loc.atlas, 0);
    var texturesLoaded = 0;
    function buffer(array, target) {
      var b = gl.createBuffer();
      gl.bindBuffer(target || gl.ARRAY_BUFFER, b);
      gl.bufferData(target || gl.ARRAY_BUFFER, array, gl.STATIC_DRAW);
      return b;
    }

    var layers = data.layers.map(function (layer) {
      var pos = decode(layer.positions, Float32Array);
      var faces = decode(layer.faces, Uint32Array);
      var out = {name: layer.name, count: layer.count, position: buffer(pos), colours: {}, visible: true,
                 positions: pos, normals: null, faces: faces};
      Object.keys(layer.colours).forEach(function (mode) {
        var bytes = decode(layer.colours[mode], Uint8Array), rgb = new Float32Array(bytes.length);
        for (var i = 0; i < bytes.length; i++) rgb[i] = bytes[i] / 255;
        out.colours[mode] = buffer(rgb);
      });
      if (layer.texture && faces) {  // a textured mesh: its atlas (a JPEG data URI), uploaded once decoded
        out.uv = buffer(decode(layer.uv, Float32Array));
        var image = new Image();
        image.onload = function () {
          out.texture = gl.createTexture();
          gl.bindTexture(gl.TEXTURE_2D, out.texture);
          gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, true);  // OBJ's v runs up from the atlas's bottom row
          gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, image);
          gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
          // any size (WebGL 1 allows non-power-of-two textures without mipmaps and with clamped edges)
          gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
          gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
          gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
          gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
          texturesLoaded += 1;
          document.body.setAttribute("data-textures-loaded", String(texturesLoaded));
          redraw();
        };
        image.src = layer.texture;
      }
      if (faces && (uintIndices || layer.count < 65536)) {
        out.normals = vertexNormals(pos, faces);
        out.normal = buffer(out.normals);
        out.index = buffer(uintIndices ? faces : new Uint16Array(faces), gl.ELEMENT_ARRAY_BUFFER);
        out.indexType = uintIndices ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;
        out.nIndices = faces.length;
      }
      return out;
    });

    // Lines: frusta, trajectory, target rings (in the plane across the up axis) and true-target crosses.
    var up = norm(data.up);
    var side = norm(cross(Math.abs(up[0]) < 0.9 ? [1, 0, 0] : [0, 1, 0], up)), side2 = cross(up, side);
    function lineSet(points, rgb) {
      var colours = new Float32Array(points.length);
      for (var i = 0; i < points.length; i += 3) colours.set(rgb, i);
      return {position: buffer(points), colour: buffer(colours), count: points.length / 3};
    }
    var frusta = data.frusta ? lineSet(decode(data.frusta, Float32Array), [0.25, 0.55, 0.95]) : null;
    var trajectoryPoints = data.trajectory ? decode(data.trajectory, Float32Array) : null;
    var trajectory = null;
    if (trajectoryPoints) {
      var seg = [];
      for (var i = 0; i + 5 < trajectoryPoints.length; i += 3)
        for (var k = 0; k < 6; k++) seg.push(trajectoryPoints[i + k]);
      trajectory = lineSet(new Float32Array(seg), [1.0, 0.6, 0.1]);
    }
    var ring = [];
    data.targets.forEach(function (t) {
      var r = t.size_mm / 2, n = 32;
      for (var j = 0; j < n; j++) {
        [j, j + 1].forEach(function (q) {
          var a = 2 * Math.PI * q / n;
          ring.push.apply(ring, add(add(t.centre, scale(side, r * Math.cos(a))), scale(side2, r * Math.sin(a))));
        });
      }
    });
    var rings = ring.length ? lineSet(new Float32Array(ring), [1.0, 0.1, 0.9]) : null;
    var cross3 = [];
    data.true_targets.forEach(function (t) {
      var r = t.size_mm / 2;
      [side, side2, up].forEach(function (d) {
        cross3.push.apply(cross3, sub(t.centre, scale(d, r)));
        cross3.push.apply(cross3, add(t.centre, scale(d, r)));
      });
    });
    var truthCrosses = cross3.length ? lineSet(new Float32Array(cross3), [0.1, 0.85, 0.3]) : null;

    var insideBox = document.getElementById("inside-view");
    var state = {yaw: 0.6, pitch: 0.7, distance: 2.6 * data.radius_mm, target: [0, 0, 0],
                 mode: (document.querySelector("input[name=colouring]:checked") || {value: "height"}).value,
                 frusta: true, targets: true, inside: !!(insideBox && insideBox.checked), fov: 60, picked: null};
    var mvp = null, eyeDir = [0, 0, 1], pending = false;

    function direction() {
      return add(add(scale(up, Math.sin(state.pitch)), scale(side, Math.cos(state.pitch) * Math.cos(state.yaw))),
                 scale(side2, Math.cos(state.pitch) * Math.sin(state.yaw)));
    }
    function eye() {
      return state.inside ? state.target : add(state.target, scale(direction(), state.distance));
    }
    function drawLines(set) {
      if (!set) return;
      gl.uniform1f(loc.lit, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, set.position);
      gl.vertexAttribPointer(loc.position, 3, gl.FLOAT, false, 0, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, set.colour);
      gl.vertexAttribPointer(loc.colour, 3, gl.FLOAT, false, 0, 0);
      gl.drawArrays(gl.LINES, 0, set.count);
    }
    function draw() {
      pending = false;
      var ratio = window.devicePixelRatio || 1;
      var w = Math.max(1, Math.round(canvas.clientWidth * ratio)), h = Math.max(1, Math.round(canvas.clientHeight * ratio));
      if (canvas.width !== w || canvas.height !== h) { canvas.width = w; canvas.height = h; overlay.width = w; overlay.height = h; }
      gl.viewport(0, 0, w, h);
      gl.clearColor(0.07, 0.08, 0.1, 1);
      gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
      gl.enable(gl.DEPTH_TEST);
      var e = eye();
      if (state.inside) {  // at the cavity's centre, looking out along -direction (drag turns the view)
        eyeDir = direction();
        mvp = multiply(perspective(state.fov * Math.PI / 180, w / h, 0.01 * data.radius_mm, 4 * data.radius_mm),
                       lookAt(e, sub(e, eyeDir), up));
      } else {
        eyeDir = norm(sub(e, state.target));
        var far = state.distance + 4 * data.radius_mm;
        mvp = multiply(perspective(45 * Math.PI / 180, w / h, Math.max(far * 1e-4, state.distance * 0.01), far),
                       lookAt(e, state.target, up));
      }
      gl.uniformMatrix4fv(loc.mvp, false, new Float32Array(mvp));
      gl.uniform3fv(loc.eyeDir, new Float32Array(eyeDir));
      gl.uniform1f(loc.pointSize, 3 * ratio);
      gl.enableVertexAttribArray(loc.position);
      gl.enableVertexAttribArray(loc.colour);
      var drawn = 0;
      layers.forEach(function (layer) {
        var colour = layer.colours[state.mode] || layer.colours.height || layer.colours[Object.keys(layer.colours)[0]];
        var textured = state.mode === "texture" && layer.texture && layer.index;
        if (!layer.visible || !colour) return;
        if (textured) {
          gl.enableVertexAttribArray(loc.uv);
          gl.bindBuffer(gl.ARRAY_BUFFER, layer.uv);
          gl.vertexAttribPointer(loc.uv, 2, gl.FLOAT, false, 0, 0);
          gl.activeTexture(gl.TEXTURE0);
          gl.bindTexture(gl.TEXTURE_2D, layer.texture);
        }
        gl.uniform1f(loc.textured, textured ? 1 : 0);
        gl.bindBuffer(gl.ARRAY_BUFFER, layer.position);
        gl.vertexAttribPointer(loc.position, 3, gl.FLOAT, false, 0, 0);
        gl.bindBuffer(gl.ARRAY_BUFFER, colour);
        gl.vertexAttribPointer(loc.colour, 3, gl.FLOAT, false, 0, 0);
        if (layer.index) {
          gl.enableVertexAttribArray(loc.normal);
          gl.bindBuffer(gl.ARRAY_BUFFER, layer.normal);
          gl.vertexAttribPointer(loc.normal, 3, gl.FLOAT, false, 0, 0);
          gl.uniform1f(loc.lit, 1);
          gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, layer.index);
          gl.drawElements(gl.TRIANGLES, layer.nIndices, layer.indexType, 0);
          gl.disableVertexAttribArray(loc.normal);
        } else {
          gl.vertexAttrib3f(loc.normal, 0, 0, 1);
          gl.uniform1f(loc.lit, 0);
          gl.drawArrays(gl.POINTS, 0, layer.count);
        }
        if (textured) gl.disableVertexAttribArray(loc.uv);
        gl.uniform1f(loc.textured, 0);
        drawn += 1;
      });
      gl.vertexAttrib3f(loc.normal, 0, 0, 1);
      gl.vertexAttrib2f(loc.uv, 0, 0);
      if (state.frusta) { drawLines(frusta); drawLines(trajectory); }
      if (state.targets) { drawLines(rings); drawLines(truthCrosses); }
      drawLabels(w, h, ratio);
      document.body.setAttribute("data-viewer", "ready");
      document.body.setAttribute("data-layers-drawn", String(drawn));
    }
    function drawLabels(w, h, ratio) {
      var ctx = overlay.getContext("2d");
      ctx.clearRect(0, 0, w, h);
      if (state.picked) {
        var q = project(mvp, state.picked);
        if (q) {
          ctx.strokeStyle = "#ff1ae6"; ctx.lineWidth = 2 * ratio;
          ctx.beginPath(); ctx.arc((q[0] + 1) / 2 * w, (1 - q[1]) / 2 * h, 7 * ratio, 0, 2 * Math.PI); ctx.stroke();
        }
      }
      if (!state.targets) return;
      ctx.font = (12 * ratio) + "px sans-serif";
      ctx.fillStyle = "#ff5cf0";
      data.targets.forEach(function (t) {
        var p = project(mvp, t.centre);
        if (p) ctx.fillText(String(t.label), (p[0] + 1) / 2 * w + 6 * ratio, (1 - p[1]) / 2 * h - 6 * ratio);
      });
    }
    function redraw() { if (!pending) { pending = true; window.requestAnimationFrame(draw); } }

    // --- the explorer: which frames saw a clicked spot ---
    var explorer = data.explorer;
    var cameraCentroid = [0, 0, 0];
    if (explorer) {
      explorer.frames.forEach(function (f) {
        var R = f.R, t = f.t;  // centre = -R^T t
        var c = [-(R[0] * t[0] + R[3] * t[1] + R[6] * t[2]), -(R[1] * t[0] + R[4] * t[1] + R[7] * t[2]),
                 -(R[2] * t[0] + R[5] * t[1] + R[8] * t[2])];
        f.centre = c;
        cameraCentroid = add(cameraCentroid, scale(c, 1 / explorer.frames.length));
      });
    }
    // From inside, start looking where the scope looked most: along the cameras' mean optical axis
    var lookYaw = 0.6, lookPitch = 0.7;
    if (explorer && insideBox) {
      var axis = [0, 0, 0];
      explorer.frames.forEach(function (f) { axis = add(axis, [f.R[6], f.R[7], f.R[8]]); });
      var back = scale(norm(axis), -1);  // direction() points against the line of sight
      lookPitch = Math.asin(Math.max(-1, Math.min(1, dot(back, up))));
      lookYaw = Math.atan2(dot(back, side2), dot(back, side));
      state.yaw = lookYaw; state.pitch = lookPitch;
    }
    // The vertex drawn nearest the eye within a few pixels of the click, with its normal (meshes only).
    function pick(px, py) {
      var rect = canvas.getBoundingClientRect(), best = null, reach = 8;
      layers.forEach(function (layer) {
        if (!layer.visible) return;
        var pos = layer.positions;
        for (var i = 0; i < pos.length; i += 3) {
          var q = project(mvp, [pos[i], pos[i + 1], pos[i + 2]]);
          if (!q || Math.abs(q[0]) > 1 || Math.abs(q[1]) > 1) continue;
          var dx = (q[0] + 1) / 2 * rect.width - px, dy = (1 - q[1]) / 2 * rect.height - py;
          if (dx * dx + dy * dy > reach * reach || (best && q[2] >= best.depth)) continue;
          best = {depth: q[2], point: [pos[i], pos[i + 1], pos[i + 2]],
                  normal: layer.normals ? [layer.normals[i], layer.normals[i + 1], layer.normals[i + 2]] : null};
        }
      });
      return best;
    }
    // Whether a drawn mesh crosses the segment from a camera's centre to the spot before the spot: a
    // uniform grid over each mesh's triangles (built on the first click), walked cell by cell along the
    // segment (Amanatides-Woo), Moller-Trumbore on the triangles of the cells it crosses, each once; a hit
    // within 1e-3 of the distance is the spot's own surface. Every triangle, one by one, cost ~70 ms per
    // frame on a 400,000-face wall (docs/report.md).
    function buildGrid(layer) {
      var v = layer.positions, f = layer.faces, nf = f.length / 3, lo = [Infinity, Infinity, Infinity],
          hi = [-Infinity, -Infinity, -Infinity], i, a, k;
      for (i = 0; i < v.length; i += 3) for (a = 0; a < 3; a++) {
        lo[a] = Math.min(lo[a], v[i + a]); hi[a] = Math.max(hi[a], v[i + a]);
      }
      var n = Math.max(1, Math.min(128, Math.round(Math.cbrt(nf) / 1.5))), size = [];
      for (a = 0; a < 3; a++) {
        var pad = 1e-6 * (hi[a] - lo[a] + 1);
        lo[a] -= pad; hi[a] += pad; size[a] = (hi[a] - lo[a]) / n;
      }
      function cellOf(x, axis) { return Math.max(0, Math.min(n - 1, Math.floor((x - lo[axis]) / size[axis]))); }
      function range(k) {  // the cells of triangle k's box: [x0, x1, y0, y1, z0, z1]
        var r = [];
        for (var axis = 0; axis < 3; axis++) {
          var p0 = v[f[k] * 3 + axis], p1 = v[f[k + 1] * 3 + axis], p2 = v[f[k + 2] * 3 + axis];
          r.push(cellOf(Math.min(p0, p1, p2), axis), cellOf(Math.max(p0, p1, p2), axis));
        }
        return r;
      }
      var start = new Int32Array(n * n * n + 1), pass, x, y, z;
      for (pass = 0; pass < 2; pass++) {
        var items = pass ? new Int32Array(start[n * n * n]) : null, fill = pass ? start.slice(0, n * n * n) : null;
        for (k = 0; k < f.length; k += 3) {
          var r = range(k);
          for (z = r[4]; z <= r[5]; z++) for (y = r[2]; y <= r[3]; y++) for (x = r[0]; x <= r[1]; x++) {
            var cell = (z * n + y) * n + x;
            if (pass) items[fill[cell]++] = k; else start[cell + 1] += 1;
          }
        }
        if (!pass) for (i = 0; i < n * n * n; i++) start[i + 1] += start[i];
      }
      return {lo: lo, size: size, n: n, start: start, items: items, stamp: new Int32Array(nf), query: 0};
    }
    function hitDistance(v, f, k, from, dx, dy, dz) {  // Moller-Trumbore in scalars; -1 for no hit
      var a = f[k] * 3, b = f[k + 1] * 3, c = f[k + 2] * 3;
      var ax = v[a], ay = v[a + 1], az = v[a + 2];
      var e1x = v[b] - ax, e1y = v[b + 1] - ay, e1z = v[b + 2] - az;
      var e2x = v[c] - ax, e2y = v[c + 1] - ay, e2z = v[c + 2] - az;
      var hx = dy * e2z - dz * e2y, hy = dz * e2x - dx * e2z, hz = dx * e2y - dy * e2x;
      var det = e1x * hx + e1y * hy + e1z * hz;
      if (det < 1e-12 && det > -1e-12) return -1;
      var inv = 1 / det, sx = from[0] - ax, sy = from[1] - ay, sz = from[2] - az;
      var u = (sx * hx + sy * hy + sz * hz) * inv;
      if (u < 0 || u > 1) return -1;
      var qx = sy * e1z - sz * e1y, qy = sz * e1x - sx * e1z, qz = sx * e1y - sy * e1x;
      var w = (dx * qx + dy * qy + dz * qz) * inv;
      if (w < 0 || u + w > 1) return -1;
      return (e2x * qx + e2y * qy + e2z * qz) * inv;
    }
    function blocks(layer, from, d, limit) {
      var g = layer.grid || (layer.grid = buildGrid(layer)), n = g.n, t0 = 0, t1 = limit, a;
      for (a = 0; a < 3; a++) {  // clip the segment to the grid's box
        if (Math.abs(d[a]) < 1e-12) {
          if (from[a] < g.lo[a] || from[a] > g.lo[a] + n * g.size[a]) return false;
        } else {
          var ta = (g.lo[a] - from[a]) / d[a], tb = (g.lo[a] + n * g.size[a] - from[a]) / d[a];
          t0 = Math.max(t0, Math.min(ta, tb)); t1 = Math.min(t1, Math.max(ta, tb));
        }
      }
      if (t0 > t1) return false;
      var cell = [], step = [], tMax = [], tDelta = [], query = ++g.query;
      for (a = 0; a < 3; a++) {
        cell[a] = Math.max(0, Math.min(n - 1, Math.floor((from[a] + d[a] * t0 - g.lo[a]) / g.size[a])));
        step[a] = d[a] > 0 ? 1 : -1;
        tMax[a] = Math.abs(d[a]) < 1e-12 ? Infinity : (g.lo[a] + (cell[a] + (d[a] > 0 ? 1 : 0)) * g.size[a] - from[a]) / d[a];
        tDelta[a] = Math.abs(d[a]) < 1e-12 ? Infinity : g.size[a] / Math.abs(d[a]);
      }
      var v = layer.positions, f = layer.faces;
      for (;;) {
        var c = (cell[2] * n + cell[1]) * n + cell[0];
        for (var j = g.start[c]; j < g.start[c + 1]; j++) {
          var k = g.items[j];
          if (g.stamp[k / 3] === query) continue;
          g.stamp[k / 3] = query;
          var t = hitDistance(v, f, k, from, d[0], d[1], d[2]);
          if (t > 0 && t < limit) return true;
        }
        a = tMax[0] < tMax[1] ? (tMax[0] < tMax[2] ? 0 : 2) : (tMax[1] < tMax[2] ? 1 : 2);
        if (tMax[a] > t1) return false;
        cell[a] += step[a];
        if (cell[a] < 0 || cell[a] >= n) return false;
        tMax[a] += tDelta[a];
      }
    }
    function occluded(from, p) {
      var d = sub(p, from), distance = Math.sqrt(dot(d, d));
      d = scale(d, 1 / distance);
      return layers.some(function (layer) {
        return layer.visible && layer.faces && blocks(layer, from, d, (1 - 1e-3) * distance);
      });
    }
    // A camera-frame point's pixel through the dataset's lens (scope3d.sensor.camera_models: the pinhole
    // family with OpenCV's radial, tangential and rational terms, or the Kannala-Brandt fisheye), or null
    // where the lens does not see it (behind a pinhole; past the fisheye's field).
    function projectPoint(c, x, y, z) {
      var p = {}, a, b;
      c.param_names.forEach(function (name, i) { p[name] = c.params[i]; });
      if (c.fisheye) {
        var rho = Math.sqrt(x * x + y * y), theta = Math.atan2(rho, z);
        if (!(theta < c.max_half_angle_rad) || rho === 0) return rho === 0 && z > 0 ? [p.cx, p.cy] : null;
        var t2 = theta * theta;
        var td = theta * (1 + t2 * (p.k1 + t2 * (p.k2 + t2 * (p.k3 + t2 * p.k4))));
        a = td * x / rho; b = td * y / rho;
      } else {
        if (!(z > 0)) return null;
        var xn = x / z, yn = y / z, r2 = xn * xn + yn * yn;
        var num = 1 + (p.k1 || 0) * r2 + (p.k2 || 0) * r2 * r2 + (p.k3 || 0) * r2 * r2 * r2;
        var den = 1 + (p.k4 || 0) * r2 + (p.k5 || 0) * r2 * r2 + (p.k6 || 0) * r2 * r2 * r2;
        var radial = num / den, p1 = p.p1 || 0, p2 = p.p2 || 0;
        a = xn * radial + 2 * p1 * xn * yn + p2 * (r2 + 2 * xn * xn);
        b = yn * radial + p1 * (r2 + 2 * yn * yn) + 2 * p2 * xn * yn;
      }
      return [p.fx * a + p.cx, p.fy * b + p.cy];
    }
    // Frames whose image holds the spot (through the lens, inside the circular field), whose centre lies on the
    // side of the surface the normal points to (the normal turned towards the cameras' centroid) and
    // whose view of it no drawn mesh blocks.
    function framesSeeing(p, normal) {
      var c = explorer.camera, seen = [];
      if (normal && dot(normal, sub(cameraCentroid, p)) < 0) normal = scale(normal, -1);
      explorer.frames.forEach(function (f, index) {
        var R = f.R, t = f.t;
        var x = R[0] * p[0] + R[1] * p[1] + R[2] * p[2] + t[0];
        var y = R[3] * p[0] + R[4] * p[1] + R[5] * p[2] + t[1];
        var z = R[6] * p[0] + R[7] * p[1] + R[8] * p[2] + t[2];
        var uv = projectPoint(c, x, y, z);
        if (uv === null) return;
        var u = uv[0], v = uv[1];
        if (u < -0.5 || v < -0.5 || u > c.width - 0.5 || v > c.height - 0.5) return;
        if (c.mask_radius_px !== null) {
          var du = u - (c.width - 1) / 2, dv = v - (c.height - 1) / 2;
          if (du * du + dv * dv > c.mask_radius_px * c.mask_radius_px) return;
        }
        if (normal && dot(normal, sub(f.centre, p)) <= 0) return;
        if (occluded(f.centre, p)) return;
        seen.push({index: index, name: f.name, u: u, v: v});
      });
      return seen;
    }
    function explore(px, py) {
      var started = window.performance.now();
      var hit = pick(px, py);
      var panel = document.getElementById("explorer-frames");
      state.picked = hit ? hit.point : null;
      if (!hit) {
        panel.textContent = "No surface under the click.";
        document.body.setAttribute("data-picked", JSON.stringify(null));
        redraw();
        return;
      }
      var seen = framesSeeing(hit.point, hit.normal);
      var world = add(hit.point, explorer.centre_mm), c = explorer.camera;
      panel.textContent = "";
      var head = document.createElement("p");
      head.textContent = "Spot (" + world.map(function (v) { return v.toFixed(2); }).join(", ") + ") mm, seen by " +
        seen.length + " frame" + (seen.length === 1 ? "" : "s") + ":";
      panel.appendChild(head);
      seen.forEach(function (s) {
        var figure = document.createElement("figure"), caption = document.createElement("figcaption");
        var picture = explorer.frames[s.index].picture;
        if (picture) {
          var holder = document.createElement("div"), img = document.createElement("img"), spot = document.createElement("span");
          holder.style.position = "relative"; holder.style.display = "inline-block";
          img.src = picture; img.alt = s.name;
          spot.className = "spot";
          spot.style.left = (100 * (s.u + 0.5) / c.width) + "%"; spot.style.top = (100 * (s.v + 0.5) / c.height) + "%";
          holder.appendChild(img); holder.appendChild(spot); figure.appendChild(holder);
        }
        caption.textContent = s.name + " (" + s.u.toFixed(0) + ", " + s.v.toFixed(0) + ") px";
        figure.appendChild(caption);
        panel.appendChild(figure);
      });
      document.body.setAttribute("data-picked", JSON.stringify({
        point_mm: world, frames: seen.map(function (s) { return s.name; }),
        pixels: seen.map(function (s) { return [s.u, s.v]; })}));
      document.body.setAttribute("data-explore-ms", String(window.performance.now() - started));
      redraw();
    }

    var drag = null;
    canvas.addEventListener("contextmenu", function (ev) { ev.preventDefault(); });
    canvas.addEventListener("mousedown", function (ev) {
      drag = {x: ev.clientX, y: ev.clientY, pan: ev.shiftKey || ev.button === 2, x0: ev.clientX, y0: ev.clientY};
    });
    window.addEventListener("mouseup", function (ev) {
      // a click (not a drag) on the view explores the spot under it
      if (drag && explorer && !drag.pan && Math.abs(ev.clientX - drag.x0) + Math.abs(ev.clientY - drag.y0) < 4) {
        var rect = canvas.getBoundingClientRect();
        explore(ev.clientX - rect.left, ev.clientY - rect.top);
      }
      drag = null;
    });
    window.addEventListener("mousemove", function (ev) {
      if (!drag) return;
      var dx = ev.clientX - drag.x, dy = ev.clientY - drag.y;
      drag.x = ev.clientX; drag.y = ev.clientY;
      if (drag.pan) {
        var e = eye(), forward = norm(sub(state.target, e)), right = norm(cross(forward, up)), upScreen = cross(right, forward);
        var k = state.distance / canvas.clientHeight;
        state.target = add(state.target, add(scale(right, -dx * k), scale(upScreen, dy * k)));
      } else {
        var turn = state.inside ? -0.005 * state.fov / 60 : 0.01;  // from inside the view turns with the drag
        state.yaw -= dx * turn;
        state.pitch = Math.max(-1.55, Math.min(1.55, state.pitch + dy * turn));
      }
      redraw();
    });
    canvas.addEventListener("wheel", function (ev) {
      ev.preventDefault();
      if (state.inside) state.fov = Math.max(10, Math.min(110, state.fov * Math.exp(ev.deltaY * 0.001)));
      else state.distance *= Math.exp(ev.deltaY * 0.001);
      redraw();
    }, {passive: false});
    document.querySelectorAll("input[name=colouring]").forEach(function (input) {
      input.addEventListener("change", function () { state.mode = input.value; showScale(); redraw(); });
    });
    document.querySelectorAll("input[data-layer]").forEach(function (input) {
      input.addEventListener("change", function () {
        layers[Number(input.getAttribute("data-layer"))].visible = input.checked; redraw();
      });
    });
    document.getElementById("show-frusta").addEventListener("change", function (ev) { state.frusta = ev.target.checked; redraw(); });
    document.getElementById("show-targets").addEventListener("change", function (ev) { state.targets = ev.target.checked; redraw(); });
    document.getElementById("reset-view").addEventListener("click", function () {
      state.yaw = state.inside ? lookYaw : 0.6; state.pitch = state.inside ? lookPitch : 0.7;
      state.distance = 2.6 * data.radius_mm; state.target = [0, 0, 0]; state.fov = 60; redraw();
    });
    if (insideBox) insideBox.addEventListener("change", function () { state.inside = insideBox.checked; redraw(); });
    // slowly alternate the reflectance texture and the texture with fluorescence (reference sec. 4.5)
    var alternateBox = document.getElementById("alternate-modes"), alternateTimer = null;
    function setMode(mode) {
      state.mode = mode;
      var radio = document.querySelector("input[name=colouring][value=" + mode + "]");
      if (radio) radio.checked = true;
      showScale(); redraw();
    }
    if (alternateBox) alternateBox.addEventListener("change", function () {
      if (alternateTimer) { window.clearInterval(alternateTimer); alternateTimer = null; }
      if (alternateBox.checked) alternateTimer = window.setInterval(function () {
        setMode(state.mode === "texture" ? "multimodal" : "texture");
      }, 1500);
    });
    function showScale() {
      document.querySelectorAll(".colour-scale").forEach(function (el) {
        el.hidden = el.getAttribute("data-mode") !== state.mode;
      });
    }
    window.addEventListener("resize", redraw);
    showScale();
    draw();
  }

  if (document.readyState === "loading") document.addEventListener("DOMContentLoaded", start);
  else start();
})();
