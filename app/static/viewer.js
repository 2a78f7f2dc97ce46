// Keystone's view-synthesis viewer: five grey + depth (GD) images drawn as textured meshes in raw
// WebGL 1 and blended by the virtual camera's distance to each of v0..v4 (KeystoneDepth, section 6).
// No build step, no libraries.
//
// Conventions (pipeline/view_stage.py, views.json): world = v0's camera frame; cameras look down -z
// with y up; x_cam = R x_world + t; pixel (u, v) with depth D is ((u-cx) D/f, -(v-cy) D/f, -D) in its
// camera, cx = (W-1)/2, cy = (H-1)/2. Matrices here are row-major arrays of 16 and are transposed
// when uploaded (WebGL 1 wants column-major).
(function () {
  "use strict";

  var canvas = document.getElementById("viewer-canvas");
  var statusLine = document.getElementById("viewer-status");
  var config = JSON.parse(document.getElementById("viewer-config").textContent);
  var MAX_VERTICES = 65000; // one 16-bit index buffer per mesh

  function say(text) { statusLine.textContent = text; }

  // ------------------------------------------------------------------------------- small maths
  function multiply(a, b) {
    var out = new Array(16);
    for (var i = 0; i < 4; i++) {
      for (var j = 0; j < 4; j++) {
        var s = 0;
        for (var k = 0; k < 4; k++) s += a[i * 4 + k] * b[k * 4 + j];
        out[i * 4 + j] = s;
      }
    }
    return out;
  }

  function rigid(R, t) { // [[R t] [0 1]] from a 3x3 (array of rows) and a 3-vector
    return [R[0][0], R[0][1], R[0][2], t[0], R[1][0], R[1][1], R[1][2], t[1],
            R[2][0], R[2][1], R[2][2], t[2], 0, 0, 0, 1];
  }

  function cameraToWorld(R, t) { // the inverse of x_cam = R x_world + t: x_world = R^T (x_cam - t)
    var Rt = [[R[0][0], R[1][0], R[2][0]], [R[0][1], R[1][1], R[2][1]], [R[0][2], R[1][2], R[2][2]]];
    var c = [0, 1, 2].map(function (i) { return -(Rt[i][0] * t[0] + Rt[i][1] * t[1] + Rt[i][2] * t[2]); });
    return rigid(Rt, c);
  }

  function sub(a, b) { return [a[0] - b[0], a[1] - b[1], a[2] - b[2]]; }
  function cross(a, b) { return [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]]; }
  function normalise(a) { var n = Math.hypot(a[0], a[1], a[2]); return [a[0] / n, a[1] / n, a[2] / n]; }

  function lookAt(eye, target, up) { // as pipeline.views.look_at: rows s, u, -f; t = -R eye
    var f = normalise(sub(target, eye));
    var s = normalise(cross(f, up));
    var u = cross(s, f);
    var R = [s, u, [-f[0], -f[1], -f[2]]];
    var t = R.map(function (row) { return -(row[0] * eye[0] + row[1] * eye[1] + row[2] * eye[2]); });
    return rigid(R, t);
  }

  function projection(focal, width, height, near, far) { // pixel focal, principal point at the centre
    return [2 * focal / width, 0, 0, 0, 0, 2 * focal / height, 0, 0,
            0, 0, (near + far) / (near - far), 2 * near * far / (near - far), 0, 0, -1, 0];
  }

  function transpose(m) {
    var out = new Float32Array(16);
    for (var i = 0; i < 4; i++) for (var j = 0; j < 4; j++) out[j * 4 + i] = m[i * 4 + j];
    return out;
  }

  // ---------------------------------------------------------------------------------- loading
  function parseNpy(buffer) { // numpy .npy, little-endian float32, C order, 2-D
    var bytes = new Uint8Array(buffer);
    if (bytes[0] !== 0x93 || String.fromCharCode.apply(null, bytes.subarray(1, 6)) !== "NUMPY") {
      throw new Error("a depth file is not a .npy array");
    }
    var view = new DataView(buffer);
    var major = bytes[6];
    var headerLength = major === 1 ? view.getUint16(8, true) : view.getUint32(8, true);
    var start = (major === 1 ? 10 : 12) + headerLength;
    var header = new TextDecoder("latin1").decode(bytes.subarray(major === 1 ? 10 : 12, start));
    if (header.indexOf("'<f4'") < 0 || header.indexOf("'fortran_order': False") < 0) {
      throw new Error("a depth file is not little-endian float32 in C order: " + header);
    }
    var shape = /'shape': \((\d+), (\d+)\)/.exec(header);
    if (!shape) throw new Error("a depth file is not 2-D: " + header);
    return { height: +shape[1], width: +shape[2], values: new Float32Array(buffer.slice(start)) };
  }

  function loadImage(url) {
    return new Promise(function (resolve, reject) {
      var image = new Image();
      image.onload = function () { resolve(image); };
      image.onerror = function () { reject(new Error("cannot load " + url)); };
      image.src = url;
    });
  }

  function loadDepth(url) {
    return fetch(url, { credentials: "same-origin" }).then(function (response) {
      if (!response.ok) throw new Error("cannot load " + url + ": " + response.status);
      return response.arrayBuffer();
    }).then(parseNpy);
  }

  // ------------------------------------------------------------------------------------ WebGL
  var VERTEX = [
    "attribute vec2 a_pixel;", "attribute float a_depth;",
    "uniform mat4 u_modelView;", "uniform mat4 u_projection;",
    "uniform vec2 u_principal;", "uniform vec2 u_size;", "uniform float u_focal;",
    "varying vec2 v_uv;",
    "void main() {",
    "  vec3 p = vec3((a_pixel.x - u_principal.x) * a_depth / u_focal,",
    "                -(a_pixel.y - u_principal.y) * a_depth / u_focal, -a_depth);",
    "  gl_Position = u_projection * u_modelView * vec4(p, 1.0);",
    "  v_uv = (a_pixel + 0.5) / u_size;",
    "}"].join("\n");
  // Two sums in one RGBA target: (R, G) = (sum w g, sum w) over the views the viewpoint is near,
  // (B, A) = the same with a small equal weight for every view. Where no near view's mesh covers a
  // pixel (a dropped triangle at a depth edge, or past its border), any other view's mesh fills it.
  var FRAGMENT = [
    "precision mediump float;",
    "uniform sampler2D u_image;", "uniform float u_weight;", "uniform float u_floor;", "varying vec2 v_uv;",
    "void main() {",
    "  float grey = texture2D(u_image, v_uv).r;",
    "  gl_FragColor = vec4(grey * u_weight, u_weight, grey * u_floor, u_floor);",
    "}"].join("\n");
  var RESOLVE_VERTEX = [
    "attribute vec2 a_corner;", "varying vec2 v_uv;",
    "void main() { v_uv = a_corner * 0.5 + 0.5; gl_Position = vec4(a_corner, 0.0, 1.0); }"].join("\n");
  var RESOLVE_FRAGMENT = [
    "precision mediump float;", "uniform sampler2D u_sum;", "varying vec2 v_uv;",
    "void main() {",
    "  vec4 sum = texture2D(u_sum, v_uv);",
    "  float grey = sum.g > 0.004 ? sum.r / sum.g : (sum.a > 0.004 ? sum.b / sum.a : 0.067);",
    "  gl_FragColor = vec4(vec3(grey), 1.0);",
    "}"].join("\n");

  function compile(gl, vertexSource, fragmentSource) {
    function shader(type, source) {
      var s = gl.createShader(type);
      gl.shaderSource(s, source);
      gl.compileShader(s);
      if (!gl.getShaderParameter(s, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(s));
      return s;
    }
    var program = gl.createProgram();
    gl.attachShader(program, shader(gl.VERTEX_SHADER, vertexSource));
    gl.attachShader(program, shader(gl.FRAGMENT_SHADER, fragmentSource));
    gl.linkProgram(program);
    if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
    return program;
  }

  // A grid mesh over one GD image: a vertex every `step` px, triangles dropped where their
  // vertices' depths differ by more than maxRelativeStep (the paper's 0.1): depth discontinuities.
  function buildMesh(gl, depth, maxRelativeStep) {
    var W = depth.width, H = depth.height;
    var step = Math.max(1, Math.ceil(Math.sqrt(W * H / MAX_VERTICES)));
    var xs = [], ys = [];
    for (var x = 0; x < W - 1; x += step) xs.push(x);
    xs.push(W - 1);
    for (var y = 0; y < H - 1; y += step) ys.push(y);
    ys.push(H - 1);
    var nx = xs.length, ny = ys.length;
    var pixels = new Float32Array(nx * ny * 2), depths = new Float32Array(nx * ny);
    for (var j = 0; j < ny; j++) {
      for (var i = 0; i < nx; i++) {
        var k = j * nx + i;
        pixels[2 * k] = xs[i];
        pixels[2 * k + 1] = ys[j];
        depths[k] = depth.values[ys[j] * W + xs[i]];
      }
    }
    function keep(a, b, c) {
      var da = depths[a], db = depths[b], dc = depths[c];
      var lo = Math.min(da, db, dc), hi = Math.max(da, db, dc);
      return lo > 0 && isFinite(hi) && hi - lo <= maxRelativeStep * lo;
    }
    var indices = [];
    for (j = 0; j < ny - 1; j++) {
      for (i = 0; i < nx - 1; i++) {
        var p00 = j * nx + i, p01 = p00 + 1, p10 = p00 + nx, p11 = p10 + 1;
        if (keep(p00, p01, p10)) indices.push(p00, p01, p10);
        if (keep(p01, p11, p10)) indices.push(p01, p11, p10);
      }
    }
    function buffer(target, data) {
      var b = gl.createBuffer();
      gl.bindBuffer(target, b);
      gl.bufferData(target, data, gl.STATIC_DRAW);
      return b;
    }
    return {
      pixels: buffer(gl.ARRAY_BUFFER, pixels), depths: buffer(gl.ARRAY_BUFFER, depths),
      indices: buffer(gl.ELEMENT_ARRAY_BUFFER, new Uint16Array(indices)), count: indices.length,
    };
  }

  function greyTexture(gl, image) {
    var texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.LUMINANCE, gl.LUMINANCE, gl.UNSIGNED_BYTE, image);
    // Non-power-of-two sizes: no mipmaps, clamped (WebGL 1's rule).
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return texture;
  }

  function accumulationTarget(gl, width, height) {
    var texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, width, height, 0, gl.RGBA, gl.UNSIGNED_BYTE, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    var depth = gl.createRenderbuffer();
    gl.bindRenderbuffer(gl.RENDERBUFFER, depth);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_STENCIL, width, height);
    var framebuffer = gl.createFramebuffer();
    gl.bindFramebuffer(gl.FRAMEBUFFER, framebuffer);
    gl.framebufferTexture2D(gl.FRAMEBUFFER, gl.COLOR_ATTACHMENT0, gl.TEXTURE_2D, texture, 0);
    gl.framebufferRenderbuffer(gl.FRAMEBUFFER, gl.DEPTH_STENCIL_ATTACHMENT, gl.RENDERBUFFER, depth);
    if (gl.checkFramebufferStatus(gl.FRAMEBUFFER) !== gl.FRAMEBUFFER_COMPLETE) {
      throw new Error("this browser cannot render into a texture");
    }
    gl.bindFramebuffer(gl.FRAMEBUFFER, null);
    return { texture: texture, framebuffer: framebuffer };
  }

  // ---------------------------------------------------------------------------------- viewing
  // Blending weights: linear fall-off with the distance from the virtual camera to each view's
  // centre, zero at the distance between v0 and a corner (r sqrt 2); normalised to sum to 1. Every
  // point of the quad is within r of some view, so some weight is always positive.
  function blendWeights(eye) {
    var reach = config.quadRadius * Math.SQRT2;
    var weights = config.views.map(function (view) {
      var d = Math.hypot(eye[0] - view.centre[0], eye[1] - view.centre[1], eye[2] - view.centre[2]);
      return Math.max(0, 1 - d / reach);
    });
    var total = weights.reduce(function (a, b) { return a + b; }, 0) || 1;
    return weights.map(function (w) { return w / total; });
  }

  function start(gl, images, depths) {
    var W = config.width, H = config.height;
    var scale = Math.min(2, window.devicePixelRatio || 1);
    canvas.width = Math.round(W * scale);
    canvas.height = Math.round(H * scale);
    var meshProgram = compile(gl, VERTEX, FRAGMENT);
    var resolveProgram = compile(gl, RESOLVE_VERTEX, RESOLVE_FRAGMENT);
    var views = config.views.map(function (view, i) {
      if (depths[i].width !== W || depths[i].height !== H) throw new Error("view " + view.name + " has the wrong size");
      return {
        toWorld: cameraToWorld(view.rotation, view.translation), focal: view.focal,
        mesh: buildMesh(gl, depths[i], config.maxRelativeStep), texture: greyTexture(gl, images[i]),
      };
    });
    var target = accumulationTarget(gl, canvas.width, canvas.height);
    var corner = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, corner);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array([-1, -1, 3, -1, -1, 3]), gl.STATIC_DRAW);

    var near = Math.max(config.depthRange[0] * 0.5, 1e-9), far = config.depthRange[1] * 2 + near;
    var focal = Math.max.apply(null, config.views.map(function (v) { return v.focal; }));
    var proj = transpose(projection(focal, W, H, near, far));
    var loc = {
      pixel: gl.getAttribLocation(meshProgram, "a_pixel"), depth: gl.getAttribLocation(meshProgram, "a_depth"),
      modelView: gl.getUniformLocation(meshProgram, "u_modelView"),
      projection: gl.getUniformLocation(meshProgram, "u_projection"),
      principal: gl.getUniformLocation(meshProgram, "u_principal"), size: gl.getUniformLocation(meshProgram, "u_size"),
      focal: gl.getUniformLocation(meshProgram, "u_focal"), image: gl.getUniformLocation(meshProgram, "u_image"),
      weight: gl.getUniformLocation(meshProgram, "u_weight"), floor: gl.getUniformLocation(meshProgram, "u_floor"),
      corner: gl.getAttribLocation(resolveProgram, "a_corner"), sum: gl.getUniformLocation(resolveProgram, "u_sum"),
    };

    function draw(eye) {
      var viewMatrix = lookAt(eye, config.sceneCentre, [0, 1, 0]);
      var weights = blendWeights(eye);
      gl.bindFramebuffer(gl.FRAMEBUFFER, target.framebuffer);
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      gl.useProgram(meshProgram);
      gl.uniformMatrix4fv(loc.projection, false, proj);
      gl.uniform2f(loc.principal, (W - 1) / 2, (H - 1) / 2);
      gl.uniform2f(loc.size, W, H);
      gl.uniform1i(loc.image, 0);
      gl.enable(gl.DEPTH_TEST);
      gl.enableVertexAttribArray(loc.pixel);
      gl.enableVertexAttribArray(loc.depth);
      views.forEach(function (view, i) {
        if (view.mesh.count === 0) return;
        gl.uniformMatrix4fv(loc.modelView, false, transpose(multiply(viewMatrix, view.toWorld)));
        gl.uniform1f(loc.focal, view.focal);
        gl.uniform1f(loc.weight, weights[i] < 1e-3 ? 0 : weights[i]);
        gl.uniform1f(loc.floor, 1 / views.length); // the five floor weights sum to 1: no saturation
        gl.bindBuffer(gl.ARRAY_BUFFER, view.mesh.pixels);
        gl.vertexAttribPointer(loc.pixel, 2, gl.FLOAT, false, 0, 0);
        gl.bindBuffer(gl.ARRAY_BUFFER, view.mesh.depths);
        gl.vertexAttribPointer(loc.depth, 1, gl.FLOAT, false, 0, 0);
        gl.bindBuffer(gl.ELEMENT_ARRAY_BUFFER, view.mesh.indices);
        gl.activeTexture(gl.TEXTURE0);
        gl.bindTexture(gl.TEXTURE_2D, view.texture);
        // Each mesh hides its own far side only: a depth-only pass, then colour where the depth
        // matches, added to the sum (the meshes must not hide one another: they are blended).
        gl.clear(gl.DEPTH_BUFFER_BIT);
        gl.disable(gl.BLEND);
        gl.colorMask(false, false, false, false);
        gl.depthFunc(gl.LESS);
        gl.drawElements(gl.TRIANGLES, view.mesh.count, gl.UNSIGNED_SHORT, 0);
        gl.colorMask(true, true, true, true);
        gl.depthFunc(gl.LEQUAL);
        gl.enable(gl.BLEND);
        gl.blendFunc(gl.ONE, gl.ONE);
        gl.drawElements(gl.TRIANGLES, view.mesh.count, gl.UNSIGNED_SHORT, 0);
      });
      gl.disableVertexAttribArray(loc.pixel);
      gl.disableVertexAttribArray(loc.depth);
      gl.disable(gl.BLEND);
      gl.disable(gl.DEPTH_TEST);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.useProgram(resolveProgram);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, target.texture);
      gl.uniform1i(loc.sum, 0);
      gl.bindBuffer(gl.ARRAY_BUFFER, corner);
      gl.enableVertexAttribArray(loc.corner);
      gl.vertexAttribPointer(loc.corner, 2, gl.FLOAT, false, 0, 0);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.disableVertexAttribArray(loc.corner);
      canvas.dataset.frames = String((+canvas.dataset.frames || 0) + 1);
      canvas.dataset.weights = weights.map(function (w) { return w.toFixed(3); }).join(",");
    }

    // The viewpoint: (x, y) in [-1, 1]^2, mapped onto the quad of corner cameras (+-r, +-r, 0).
    var wanted = [0, 0], current = [0, 0], pending = false;
    function frame() {
      pending = false;
      current[0] += (wanted[0] - current[0]) * 0.35;
      current[1] += (wanted[1] - current[1]) * 0.35;
      var settled = Math.abs(wanted[0] - current[0]) < 1e-3 && Math.abs(wanted[1] - current[1]) < 1e-3;
      if (settled) current = wanted.slice();
      draw([current[0] * config.quadRadius, current[1] * config.quadRadius, 0]);
      canvas.dataset.position = current[0].toFixed(3) + "," + current[1].toFixed(3);
      canvas.dataset.moving = settled ? "0" : "1";
      if (!settled) schedule();
    }
    function schedule() {
      if (!pending) { pending = true; window.requestAnimationFrame(frame); }
    }
    function aim(x, y) {
      wanted = [Math.max(-1, Math.min(1, x)), Math.max(-1, Math.min(1, y))];
      canvas.dataset.moving = "1";
      schedule();
    }

    canvas.addEventListener("pointermove", function (event) {
      var box = canvas.getBoundingClientRect();
      aim(((event.clientX - box.left) / box.width) * 2 - 1, 1 - ((event.clientY - box.top) / box.height) * 2);
    });
    canvas.tabIndex = 0;
    canvas.addEventListener("keydown", function (event) {
      var moves = { ArrowLeft: [-0.25, 0], ArrowRight: [0.25, 0], ArrowUp: [0, 0.25], ArrowDown: [0, -0.25] };
      var move = moves[event.key];
      if (!move) return;
      event.preventDefault();
      aim(wanted[0] + move[0], wanted[1] + move[1]);
    });
    // A phone held still at any angle is the centre; tilting it 30 deg reaches a corner.
    var rest = null;
    function onTilt(event) {
      if (event.beta === null || event.gamma === null) return;
      if (rest === null) rest = [event.gamma, event.beta];
      aim((event.gamma - rest[0]) / 30, -(event.beta - rest[1]) / 30);
    }
    var motion = document.getElementById("viewer-motion");
    if (window.DeviceOrientationEvent && typeof window.DeviceOrientationEvent.requestPermission === "function") {
      motion.hidden = false; // iOS asks for permission, and only from a tap
      motion.addEventListener("click", function () {
        window.DeviceOrientationEvent.requestPermission().then(function (answer) {
          if (answer === "granted") { window.addEventListener("deviceorientation", onTilt); motion.hidden = true; }
        });
      });
    } else if ("ondeviceorientation" in window) {
      window.addEventListener("deviceorientation", onTilt);
    }

    frame();
    canvas.dataset.state = "ready";
    say("Move the pointer over the picture, drag on a touch screen, tilt a phone, or use the arrow keys.");
  }

  function fail(message, state) {
    canvas.dataset.state = state;
    say(message);
    var fallback = document.getElementById("viewer-fallback");
    if (fallback) { fallback.hidden = false; canvas.style.display = "none"; }
  }

  var gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: false, alpha: false });
  if (!gl) {
    fail("This browser has no WebGL, so the 3D view cannot be drawn.", "no-webgl");
    return;
  }
  Promise.all([
    Promise.all(config.views.map(function (v) { return loadImage(v.image); })),
    Promise.all(config.views.map(function (v) { return loadDepth(v.depth); })),
  ]).then(function (loaded) {
    start(gl, loaded[0], loaded[1]);
  }).catch(function (error) {
    fail("The 3D view could not be drawn: " + error.message, "error");
  });
})();
