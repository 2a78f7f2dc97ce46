// Keystone's view-synthesis viewer: five colour (or grey) + depth images drawn as textured meshes in
// raw WebGL 1 and blended by the virtual camera's distance to each of v0..v4 (KeystoneDepth, section 6).
// No build step, no libraries. Per view it downloads a JPEG and a small PNG of quantised inverse depth
// on the mesh grid (pipeline/stages/views.py: viewer_mesh_png), 0.3-0.5 MB a card in all.
//
// Conventions (pipeline/view_synthesis.py, views.json): world = v0's camera frame; cameras look down -z
// with y up; x_cam = R x_world + t; pixel (u, v) with depth D is ((u-cx) D/f, -(v-cy) D/f, -D) in its
// camera, cx = (W-1)/2, cy = (H-1)/2. Matrices here are row-major arrays of 16 and are transposed
// when uploaded (WebGL 1 wants column-major).
(function () {
  "use strict";

  var canvas = document.getElementById("viewer-canvas");
  var statusLine = document.getElementById("viewer-status");
  var config = JSON.parse(document.getElementById("viewer-config").textContent);

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
  function loadImage(url) {
    return new Promise(function (resolve, reject) {
      var image = new Image();
      image.onload = function () { resolve(image); };
      image.onerror = function () { reject(new Error("cannot load " + url)); };
      image.src = url;
    });
  }

  // The mesh PNG: 8-bit RGB on the mesh grid, q = 256 R + G, 1/D = lo + q / 65535 (hi - lo). A PNG
  // without colour chunks reaches a 2D canvas unchanged, so getImageData gives the bytes back.
  function loadMesh(url) {
    return loadImage(url).then(function (image) {
      var mesh = config.mesh;
      if (image.width !== mesh.columns || image.height !== mesh.rows) throw new Error("a mesh file has the wrong size");
      var scratch = document.createElement("canvas");
      scratch.width = image.width;
      scratch.height = image.height;
      var context = scratch.getContext("2d", { willReadFrequently: true });
      context.drawImage(image, 0, 0);
      var bytes = context.getImageData(0, 0, image.width, image.height).data;
      var lo = mesh.inverseDepthRange[0], span = mesh.inverseDepthRange[1] - lo;
      var depths = new Float32Array(image.width * image.height);
      for (var k = 0; k < depths.length; k++) {
        var inverse = lo + (bytes[4 * k] * 256 + bytes[4 * k + 1]) / 65535 * span;
        depths[k] = inverse > 0 ? 1 / inverse : 0;
      }
      return depths;
    });
  }

  function meshAxis(size, step) { // as pipeline.stages.views.mesh_grid: 0, step, ... and the last pixel
    var axis = [];
    for (var x = 0; x < size - 1; x += step) axis.push(x);
    if (axis[axis.length - 1] !== size - 1) axis.push(size - 1);
    return axis;
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
  // Two RGBA sums, (sum w rgb, sum w), in two targets: one over the views the viewpoint is near, one
  // with an equal weight for every view. Where no near view's mesh covers a pixel (a dropped triangle
  // at a depth edge, or past its border), any other view's mesh fills it.
  var FRAGMENT = [
    "precision mediump float;",
    "uniform sampler2D u_image;", "uniform float u_weight;", "varying vec2 v_uv;",
    "void main() {",
    "  gl_FragColor = vec4(texture2D(u_image, v_uv).rgb * u_weight, u_weight);",
    "}"].join("\n");
  var RESOLVE_VERTEX = [
    "attribute vec2 a_corner;", "varying vec2 v_uv;",
    "void main() { v_uv = a_corner * 0.5 + 0.5; gl_Position = vec4(a_corner, 0.0, 1.0); }"].join("\n");
  var RESOLVE_FRAGMENT = [
    "precision mediump float;", "uniform sampler2D u_near;", "uniform sampler2D u_all;", "varying vec2 v_uv;",
    "void main() {",
    "  vec4 near = texture2D(u_near, v_uv);",
    "  vec4 all = texture2D(u_all, v_uv);",
    // The sums are 8-bit: a weight under 0.1 would divide a quantisation step into a false colour
    // (the fringes of yellow and pink seen at depth edges); the equal-weight sum is >= 0.2 where covered.
    "  vec3 colour = near.a > 0.1 ? near.rgb / near.a : (all.a > 0.1 ? all.rgb / all.a : vec3(0.067));",
    "  gl_FragColor = vec4(colour, 1.0);",
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

  // A grid mesh over one view's depth on the mesh grid (a vertex every config.mesh.step px).
  // Triangles are dropped only at depth edges: a relative depth step above maxRelativeStep (the
  // paper's 0.1) that also stretches, i.e. whose vertices move apart by more than maxStretchPx per
  // grid step when the viewpoint moves as far as the blending reaches (r sqrt 2). A far surface with
  // noisy depth or a slanted plane has large relative steps but tiny parallax: it stays whole.
  function buildMesh(gl, depths, focal) {
    var xs = meshAxis(config.width, config.mesh.step), ys = meshAxis(config.height, config.mesh.step);
    var nx = xs.length, ny = ys.length;
    if (nx !== config.mesh.columns || ny !== config.mesh.rows) throw new Error("the mesh grid does not match");
    var pixels = new Float32Array(nx * ny * 2);
    for (var j = 0; j < ny; j++) {
      for (var i = 0; i < nx; i++) {
        var k = j * nx + i;
        pixels[2 * k] = xs[i];
        pixels[2 * k + 1] = ys[j];
      }
    }
    var useStretch = typeof config.maxStretchPx === "number"; // absent: the paper's rule alone
    var stretchScale = focal * config.quadRadius * Math.SQRT2;
    var stretchLimit = (config.maxStretchPx || 0) * config.mesh.step;
    function keep(a, b, c) {
      var da = depths[a], db = depths[b], dc = depths[c];
      var lo = Math.min(da, db, dc), hi = Math.max(da, db, dc);
      if (!(lo > 0) || !isFinite(hi)) return false;
      return hi - lo <= config.maxRelativeStep * lo || (useStretch && stretchScale * (1 / lo - 1 / hi) <= stretchLimit);
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
      pixels: buffer(gl.ARRAY_BUFFER, pixels), depths: buffer(gl.ARRAY_BUFFER, depths), dropped: (nx - 1) * (ny - 1) * 2 - indices.length / 3,
      indices: buffer(gl.ELEMENT_ARRAY_BUFFER, new Uint16Array(indices)), count: indices.length,
    };
  }

  function colourTexture(gl, image) {
    var texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.pixelStorei(gl.UNPACK_FLIP_Y_WEBGL, false);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, image); // a grey JPEG fills all three
    // Non-power-of-two sizes: no mipmaps, clamped (WebGL 1's rule).
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return texture;
  }

  function accumulationTarget(gl, width, height, depth) {
    var texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGBA, width, height, 0, gl.RGBA, gl.UNSIGNED_BYTE, null);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.NEAREST);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
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

  function start(gl, images, meshes) {
    var W = config.width, H = config.height;
    var scale = Math.min(2, window.devicePixelRatio || 1);
    canvas.width = Math.round(W * scale);
    canvas.height = Math.round(H * scale);
    var meshProgram = compile(gl, VERTEX, FRAGMENT);
    var resolveProgram = compile(gl, RESOLVE_VERTEX, RESOLVE_FRAGMENT);
    var views = config.views.map(function (view, i) {
      if (images[i].width !== W || images[i].height !== H) throw new Error("view " + view.name + " has the wrong size");
      return {
        toWorld: cameraToWorld(view.rotation, view.translation), focal: view.focal,
        mesh: buildMesh(gl, meshes[i], view.focal), texture: colourTexture(gl, images[i]),
      };
    });
    canvas.dataset.dropped = views.map(function (v) { return v.mesh.dropped; }).join(",");
    var depthBuffer = gl.createRenderbuffer(); // shared: each mesh clears it before it is drawn
    gl.bindRenderbuffer(gl.RENDERBUFFER, depthBuffer);
    gl.renderbufferStorage(gl.RENDERBUFFER, gl.DEPTH_STENCIL, canvas.width, canvas.height);
    var targets = [accumulationTarget(gl, canvas.width, canvas.height, depthBuffer),
                   accumulationTarget(gl, canvas.width, canvas.height, depthBuffer)];
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
      weight: gl.getUniformLocation(meshProgram, "u_weight"),
      corner: gl.getAttribLocation(resolveProgram, "a_corner"),
      near: gl.getUniformLocation(resolveProgram, "u_near"), all: gl.getUniformLocation(resolveProgram, "u_all"),
    };

    function accumulate(target, viewMatrix, weightOf) {
      gl.bindFramebuffer(gl.FRAMEBUFFER, target.framebuffer);
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.clearColor(0, 0, 0, 0);
      gl.clear(gl.COLOR_BUFFER_BIT);
      views.forEach(function (view, i) {
        var weight = weightOf(i);
        if (view.mesh.count === 0 || weight === 0) return;
        gl.uniformMatrix4fv(loc.modelView, false, transpose(multiply(viewMatrix, view.toWorld)));
        gl.uniform1f(loc.focal, view.focal);
        gl.uniform1f(loc.weight, weight);
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
    }

    function draw(eye) {
      var viewMatrix = lookAt(eye, config.sceneCentre, [0, 1, 0]);
      var weights = blendWeights(eye);
      gl.useProgram(meshProgram);
      gl.uniformMatrix4fv(loc.projection, false, proj);
      gl.uniform2f(loc.principal, (W - 1) / 2, (H - 1) / 2);
      gl.uniform2f(loc.size, W, H);
      gl.uniform1i(loc.image, 0);
      gl.enable(gl.DEPTH_TEST);
      gl.enableVertexAttribArray(loc.pixel);
      gl.enableVertexAttribArray(loc.depth);
      accumulate(targets[0], viewMatrix, function (i) { return weights[i] < 1e-3 ? 0 : weights[i]; });
      accumulate(targets[1], viewMatrix, function () { return 1 / views.length; }); // sums to 1: no saturation
      gl.disableVertexAttribArray(loc.pixel);
      gl.disableVertexAttribArray(loc.depth);
      gl.disable(gl.BLEND);
      gl.disable(gl.DEPTH_TEST);
      gl.bindFramebuffer(gl.FRAMEBUFFER, null);
      gl.viewport(0, 0, canvas.width, canvas.height);
      gl.useProgram(resolveProgram);
      gl.activeTexture(gl.TEXTURE0);
      gl.bindTexture(gl.TEXTURE_2D, targets[0].texture);
      gl.activeTexture(gl.TEXTURE1);
      gl.bindTexture(gl.TEXTURE_2D, targets[1].texture);
      gl.uniform1i(loc.near, 0);
      gl.uniform1i(loc.all, 1);
      gl.bindBuffer(gl.ARRAY_BUFFER, corner);
      gl.enableVertexAttribArray(loc.corner);
      gl.vertexAttribPointer(loc.corner, 2, gl.FLOAT, false, 0, 0);
      gl.drawArrays(gl.TRIANGLES, 0, 3);
      gl.disableVertexAttribArray(loc.corner);
      gl.activeTexture(gl.TEXTURE0);
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
    if (fallback) { // fetched only now: a browser with WebGL never downloads the preview
      var picture = fallback.querySelector("img");
      picture.src = picture.dataset.src;
      fallback.hidden = false;
      canvas.style.display = "none";
    }
  }

  var gl = canvas.getContext("webgl", { preserveDrawingBuffer: true, antialias: false, alpha: false });
  if (!gl) {
    fail("This browser has no WebGL, so the 3D view cannot be drawn.", "no-webgl");
    return;
  }
  Promise.all([
    Promise.all(config.views.map(function (v) { return loadImage(v.image); })),
    Promise.all(config.views.map(function (v) { return loadMesh(v.mesh); })),
  ]).then(function (loaded) {
    start(gl, loaded[0], loaded[1]);
  }).catch(function (error) {
    fail("The 3D view could not be drawn: " + error.message, "error");
  });
})();
