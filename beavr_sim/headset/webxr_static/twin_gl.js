// The twin drawn with plain WebGL 2: each geom as a simple shape or its mesh, lit from above.
//
// Poses come from the simulator in its world frame (Z up: x forward, y left, metres), 12
// numbers per geom: position, then R_world_geom row by row. T_xr_world places that world in
// the session's local-floor space (Y up, -Z forward): the world's floor on the floor, the
// robot's base WORLD_AHEAD_M in front of where the session started, facing away from you.

export const WORLD_AHEAD_M = 0.8;
// R_xr_world rows: x_xr = -y_world, y_xr = z_world, z_xr = -x_world.
const R_XR_WORLD = [0, -1, 0, 0, 0, 1, -1, 0, 0];
const T_XR_WORLD_OFFSET = [0, 0, -WORLD_AHEAD_M];

// A point of the simulator's world (Z up) in the session's space.
export function worldToXr(p) {
  const out = [0, 0, 0];
  for (let r = 0; r < 3; r++) {
    out[r] = R_XR_WORLD[3 * r] * p[0] + R_XR_WORLD[3 * r + 1] * p[1] +
      R_XR_WORLD[3 * r + 2] * p[2] + T_XR_WORLD_OFFSET[r];
  }
  return out;
}

// One draw call per mesh and view: every geom of a shape is an instance (a rotation and
// translation in rows, a scale, a colour). Draw calls, not pixels, are what a phone-class GPU
// (and a software one) pays for. The robot's meshes come once with the scene (docs/formats.md):
// each is a unit mesh in [-1, 1] of its bounding box, drawn like the cube (scale: the box's half
// extents), flat shaded from the screen-space derivatives of its position (no normals to send
// or store, and each vertex shared by its triangles); a mesh that cannot be read is drawn as
// its box.
const VERTEX_SHADER = `#version 300 es
layout(location = 0) in vec3 aPosition;
layout(location = 1) in vec3 aNormal;
layout(location = 2) in vec4 aRow0;
layout(location = 3) in vec4 aRow1;
layout(location = 4) in vec4 aRow2;
layout(location = 5) in vec3 aScale;
layout(location = 6) in vec4 aColor;
uniform mat4 uProjection;
uniform mat4 uView;
out vec3 vNormal;
out highp vec3 vPosition;
out vec4 vColor;
void main() {
  vec3 p = aPosition * aScale;
  vec3 n = aNormal / aScale;
  vec3 w = vec3(dot(aRow0.xyz, p) + aRow0.w, dot(aRow1.xyz, p) + aRow1.w,
                dot(aRow2.xyz, p) + aRow2.w);
  vNormal = vec3(dot(aRow0.xyz, n), dot(aRow1.xyz, n), dot(aRow2.xyz, n));
  vPosition = w;
  vColor = aColor;
  gl_Position = uProjection * uView * vec4(w, 1.0);
}`;

const FRAGMENT_SHADER = `#version 300 es
precision mediump float;
uniform bool uFlat;
in vec3 vNormal;
in highp vec3 vPosition;
in vec4 vColor;
out vec4 outColor;
void main() {
  // Flat: the triangle's normal, facing the viewer (highp: a pixel spans well under 1 mm).
  highp vec3 face = cross(dFdx(vPosition), dFdy(vPosition));
  vec3 n = uFlat ? vec3(normalize(face)) : normalize(vNormal);
  float light = 0.35 + 0.65 * max(dot(n, normalize(vec3(0.3, 1.0, 0.5))), 0.0);
  outColor = vec4(vColor.rgb * light, vColor.a);
}`;

// Floats per instance: 3 rows of (rotation | translation), scale (3), colour (4).
const STRIDE = 19;
const HAND_COLOUR = [0.2, 0.85, 1.0, 1.0];
// Mesh payloads (webxr_scene.encode_mesh): int16 vertices over the bounding box, then faces.
const QUANT = 32767;
const U16_VERTICES = 65536;
const MAX_TRIANGLES = 1 << 20;
const LITTLE_ENDIAN = new Uint8Array(new Uint16Array([1]).buffer)[0] === 1;

function compile(gl, type, source, label) {
  const shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) {
    throw new Error(`${label} shader: ${gl.getShaderInfoLog(shader)}`);
  }
  return shader;
}

// A linked WebGL2 program of the two shaders' sources; errors name `label`.
export function linkProgram(gl, vertexSource, fragmentSource, label) {
  const program = gl.createProgram();
  gl.attachShader(program, compile(gl, gl.VERTEX_SHADER, vertexSource, label));
  gl.attachShader(program, compile(gl, gl.FRAGMENT_SHADER, fragmentSource, label));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) {
    throw new Error(`${label} program: ${gl.getProgramInfoLog(program)}`);
  }
  return program;
}

// Instances of one mesh, grown as needed.
class Instances {
  constructor() {
    this.data = new Float32Array(STRIDE * 64);
    this.count = 0;
  }

  clear() {
    this.count = 0;
  }

  // rows: R_xr_shape row-major (9), t: translation (3), s: scale (3), rgba (4).
  push(R, t, s, rgba) {
    if (STRIDE * (this.count + 1) > this.data.length) {
      const grown = new Float32Array(this.data.length * 2);
      grown.set(this.data);
      this.data = grown;
    }
    const d = this.data, o = STRIDE * this.count++;
    for (let r = 0; r < 3; r++) {
      d[o + 4 * r] = R[3 * r];
      d[o + 4 * r + 1] = R[3 * r + 1];
      d[o + 4 * r + 2] = R[3 * r + 2];
      d[o + 4 * r + 3] = t[r];
    }
    for (let c = 0; c < 3; c++) d[o + 12 + c] = Math.max(s[c], 1e-6);
    for (let c = 0; c < 4; c++) d[o + 15 + c] = rgba[c];
  }
}

// Unit meshes: cube of half extent 1, sphere of radius 1, cylinder of radius 1 and z in [-1, 1].
function cubeMesh() {
  const positions = [], normals = [], indices = [];
  const faces = [[0, 1], [0, -1], [1, 1], [1, -1], [2, 1], [2, -1]];
  for (const [axis, sign] of faces) {
    const u = (axis + 1) % 3, v = (axis + 2) % 3, base = positions.length / 3;
    for (const [a, b] of [[-1, -1], [1, -1], [1, 1], [-1, 1]]) {
      const p = [0, 0, 0], n = [0, 0, 0];
      p[axis] = sign; p[u] = a * sign; p[v] = b; n[axis] = sign;
      positions.push(...p); normals.push(...n);
    }
    indices.push(base, base + 1, base + 2, base, base + 2, base + 3);
  }
  return { positions, normals, indices };
}

function sphereMesh(rings = 6, segments = 10) {
  const positions = [], normals = [], indices = [];
  for (let i = 0; i <= rings; i++) {
    const theta = (i / rings) * Math.PI;
    for (let j = 0; j <= segments; j++) {
      const phi = (j / segments) * 2 * Math.PI;
      const n = [Math.sin(theta) * Math.cos(phi), Math.sin(theta) * Math.sin(phi), Math.cos(theta)];
      positions.push(...n); normals.push(...n);
    }
  }
  for (let i = 0; i < rings; i++) {
    for (let j = 0; j < segments; j++) {
      const a = i * (segments + 1) + j, b = a + segments + 1;
      indices.push(a, b, a + 1, b, b + 1, a + 1);
    }
  }
  return { positions, normals, indices };
}

function cylinderMesh(segments = 12) {
  const positions = [], normals = [], indices = [];
  for (let j = 0; j <= segments; j++) {
    const phi = (j / segments) * 2 * Math.PI, c = Math.cos(phi), s = Math.sin(phi);
    positions.push(c, s, -1, c, s, 1); normals.push(c, s, 0, c, s, 0);
  }
  for (let j = 0; j < segments; j++) {
    const a = 2 * j;
    indices.push(a, a + 2, a + 1, a + 1, a + 2, a + 3);
  }
  for (const z of [-1, 1]) {
    const centre = positions.length / 3;
    positions.push(0, 0, z); normals.push(0, 0, z);
    for (let j = 0; j <= segments; j++) {
      const phi = (j / segments) * 2 * Math.PI;
      positions.push(Math.cos(phi), Math.sin(phi), z); normals.push(0, 0, z);
    }
    for (let j = 0; j < segments; j++) indices.push(centre, centre + 1 + j, centre + 2 + j);
  }
  return { positions, normals, indices };
}

function base64Bytes(text) {
  if (Uint8Array.fromBase64) return Uint8Array.fromBase64(text);
  const binary = atob(text);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes;
}

// A scene message's mesh entry -> a unit mesh: positions in [-1, 1] of its bounding box, triangle
// indices, no normals (drawn flat). Throws saying why when the entry is not a valid mesh.
export function decodeMesh(entry) {
  if (!entry || typeof entry !== "object") throw new Error("not an object");
  const n = entry.vertices, m = entry.faces;
  if (!Number.isInteger(n) || !Number.isInteger(m) || n < 3 || m < 1 || m > MAX_TRIANGLES) {
    throw new Error(`bad counts (${n} vertices, ${m} faces)`);
  }
  if (typeof entry.data !== "string") throw new Error("no data");
  const bytes = base64Bytes(entry.data);
  const start = 6 * n + ((4 - ((6 * n) % 4)) % 4);
  const wide = n > U16_VERTICES;
  if (bytes.length !== start + 3 * m * (wide ? 4 : 2)) {
    throw new Error(`${bytes.length} bytes for ${n} vertices and ${m} faces`);
  }
  // The payload is little-endian, as is every platform WebXR runs on (else: read it byte-wise).
  const view = new DataView(bytes.buffer);
  const raw = LITTLE_ENDIAN ? new Int16Array(bytes.buffer, 0, 3 * n) : null;
  const q = new Float32Array(3 * n);
  for (let i = 0; i < 3 * n; i++) {
    const v = raw ? raw[i] : view.getInt16(2 * i, true);
    if (v < -QUANT) throw new Error("vertex out of range");
    q[i] = v / QUANT;
  }
  let faces;
  if (LITTLE_ENDIAN) {
    faces = wide ? new Uint32Array(bytes.buffer, start, 3 * m)
      : new Uint16Array(bytes.buffer, start, 3 * m);
  } else {
    faces = new Uint32Array(3 * m);
    for (let i = 0; i < 3 * m; i++) {
      faces[i] = wide ? view.getUint32(start + 4 * i, true) : view.getUint16(start + 2 * i, true);
    }
  }
  for (let i = 0; i < 3 * m; i++) {
    if (faces[i] >= n) throw new Error(`face ${Math.floor(i / 3)}: vertex ${faces[i]} of ${n}`);
  }
  // Indices into a fresh array: the payload's bytes are not kept.
  return { positions: q, normals: null, indices: wide ? Uint32Array.from(faces)
    : Uint16Array.from(faces) };
}

export class TwinRenderer {
  // gl: a WebGL2 context.
  constructor(gl) {
    this.gl = gl;
    const program = linkProgram(gl, VERTEX_SHADER, FRAGMENT_SHADER, "twin");
    this.program = program;
    this.uProjection = gl.getUniformLocation(program, "uProjection");
    this.uView = gl.getUniformLocation(program, "uView");
    this.uFlat = gl.getUniformLocation(program, "uFlat");
    this.meshes = { cube: this.upload(cubeMesh()), sphere: this.upload(sphereMesh()),
      cylinder: this.upload(cylinderMesh()) };
    this.scene = { cube: new Instances(), sphere: new Instances(), cylinder: new Instances() };
    this.hands = new Instances();
    this.shapes = [];
    this.sizes = [];
    this.rgba = [];
    this.pose = new Float64Array(0);
    this.dynamic = [];
    this.meshIndex = [];
    // The scene's meshes: { mesh, instances } per entry, null where one could not be read.
    this.sceneMeshes = [];
    this.meshStats = { meshes: 0, failed: 0, triangles: 0, ms: 0, errors: [] };
  }

  upload(mesh) {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    gl.bindVertexArray(vao);
    const buffer = (target, data) => {
      const b = gl.createBuffer();
      gl.bindBuffer(target, b);
      gl.bufferData(target, data, gl.STATIC_DRAW);
      return b;
    };
    const floats = (a) => (a instanceof Float32Array ? a : new Float32Array(a));
    const buffers = [];
    buffers.push(buffer(gl.ARRAY_BUFFER, floats(mesh.positions)));
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 0, 0);
    const flat = mesh.normals === null;
    if (!flat) {
      buffers.push(buffer(gl.ARRAY_BUFFER, floats(mesh.normals)));
      gl.enableVertexAttribArray(1);
      gl.vertexAttribPointer(1, 3, gl.FLOAT, false, 0, 0);
    }
    const indices = ArrayBuffer.isView(mesh.indices) ? mesh.indices
      : new Uint16Array(mesh.indices);
    buffers.push(buffer(gl.ELEMENT_ARRAY_BUFFER, indices));
    const indexType = indices instanceof Uint32Array ? gl.UNSIGNED_INT : gl.UNSIGNED_SHORT;
    const instances = gl.createBuffer();
    buffers.push(instances);
    gl.bindBuffer(gl.ARRAY_BUFFER, instances);
    const layout = [[2, 4, 0], [3, 4, 4], [4, 4, 8], [5, 3, 12], [6, 4, 15]];
    for (const [location, size, offset] of layout) {
      gl.enableVertexAttribArray(location);
      gl.vertexAttribPointer(location, size, gl.FLOAT, false, 4 * STRIDE, 4 * offset);
      gl.vertexAttribDivisor(location, 1);
    }
    gl.bindVertexArray(null);
    return { vao, instances, count: indices.length, indexType, flat, buffers };
  }

  release(mesh) {
    const gl = this.gl;
    gl.deleteVertexArray(mesh.vao);
    for (const b of mesh.buffers) gl.deleteBuffer(b);
  }

  // The scene's meshes, each on its own: one that cannot be read is left null (its geoms are
  // drawn as their boxes) and counted in meshStats, with why.
  loadMeshes(entries) {
    for (const loaded of this.sceneMeshes) if (loaded) this.release(loaded.mesh);
    const began = performance.now();
    const stats = { meshes: 0, failed: 0, triangles: 0, ms: 0, errors: [] };
    this.sceneMeshes = (Array.isArray(entries) ? entries : []).map((entry, k) => {
      try {
        const mesh = this.upload(decodeMesh(entry));
        stats.meshes++;
        stats.triangles += entry.faces;
        return { mesh, instances: new Instances() };
      } catch (err) {
        const name = entry && typeof entry.name === "string" ? entry.name : `#${k}`;
        stats.failed++;
        stats.errors.push(`${name}: ${err.message || err}`);
        console.warn(`twin mesh ${name} not drawn (its box instead): ${err.message || err}`);
        return null;
      }
    });
    stats.ms = performance.now() - began;
    this.meshStats = stats;
  }

  get geomCount() {
    return this.shapes.length;
  }

  setScene(msg) {
    this.shapes = msg.shapes;
    this.sizes = msg.sizes;
    this.rgba = msg.rgba;
    this.pose = Float64Array.from(msg.pose);
    this.dynamic = msg.dynamic;
    this.meshIndex = Array.isArray(msg.mesh) ? msg.mesh : [];
    this.loadMeshes(msg.meshes);
    this.rebuild();
  }

  setPoses(flat) {
    const n = Math.min(this.dynamic.length, Math.floor(flat.length / 12));
    for (let k = 0; k < n; k++) {
      const i = this.dynamic[k];
      for (let c = 0; c < 12; c++) this.pose[12 * i + c] = flat[12 * k + c];
    }
    this.rebuild();
  }

  // The geoms' instances in the session's space: R_xr_geom = R_xr_world R_world_geom.
  rebuild() {
    for (const group of Object.values(this.scene)) group.clear();
    for (const loaded of this.sceneMeshes) if (loaded) loaded.instances.clear();
    const P = this.pose, R = new Array(9), t = [0, 0, 0], end = [0, 0, 0];
    for (let i = 0; i < this.shapes.length; i++) {
      const o = 12 * i;
      for (let r = 0; r < 3; r++) {
        for (let c = 0; c < 3; c++) {
          R[3 * r + c] = R_XR_WORLD[3 * r] * P[o + 3 + c] +
            R_XR_WORLD[3 * r + 1] * P[o + 6 + c] + R_XR_WORLD[3 * r + 2] * P[o + 9 + c];
        }
        t[r] = R_XR_WORLD[3 * r] * P[o] + R_XR_WORLD[3 * r + 1] * P[o + 1] +
          R_XR_WORLD[3 * r + 2] * P[o + 2] + T_XR_WORLD_OFFSET[r];
      }
      const z = this.sizes.slice(3 * i, 3 * i + 3), rgba = this.rgba.slice(4 * i, 4 * i + 4);
      const shape = this.shapes[i];
      if (shape === "mesh") {
        const loaded = this.sceneMeshes[this.meshIndex[i]];
        (loaded ? loaded.instances : this.scene.cube).push(R, t, z, rgba);
      } else if (shape === "box") {
        this.scene.cube.push(R, t, z, rgba);
      } else if (shape === "sphere") {
        this.scene.sphere.push(R, t, [z[0], z[0], z[0]], rgba);
      } else if (shape === "ellipsoid") {
        this.scene.sphere.push(R, t, z, rgba);
      } else if (shape === "cylinder" || shape === "capsule") {
        this.scene.cylinder.push(R, t, [z[0], z[0], z[1]], rgba);
        if (shape === "capsule") {
          for (const sign of [-1, 1]) {
            for (let r = 0; r < 3; r++) end[r] = t[r] + sign * z[1] * R[3 * r + 2];
            this.scene.sphere.push(R, end, [z[0], z[0], z[0]], rgba);
          }
        }
      }
    }
  }

  drawInstances(mesh, instances) {
    if (!instances.count) return;
    const gl = this.gl;
    gl.bindVertexArray(mesh.vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, mesh.instances);
    gl.bufferData(gl.ARRAY_BUFFER, instances.data.subarray(0, STRIDE * instances.count),
      gl.DYNAMIC_DRAW);
    gl.uniform1i(this.uFlat, mesh.flat ? 1 : 0);
    gl.drawElementsInstanced(gl.TRIANGLES, mesh.count, mesh.indexType, 0, instances.count);
  }

  // projection, view: column-major 4x4 (an XRView's projectionMatrix, transform.inverse.matrix).
  // points: [x, y, z, radius] in the session's space (the tracked hand joints).
  draw(projection, view, points = []) {
    const gl = this.gl;
    gl.useProgram(this.program);
    gl.enable(gl.DEPTH_TEST);
    gl.enable(gl.BLEND);
    gl.blendFunc(gl.SRC_ALPHA, gl.ONE_MINUS_SRC_ALPHA);
    gl.uniformMatrix4fv(this.uProjection, false, projection);
    gl.uniformMatrix4fv(this.uView, false, view);
    this.drawInstances(this.meshes.cube, this.scene.cube);
    this.drawInstances(this.meshes.cylinder, this.scene.cylinder);
    for (const loaded of this.sceneMeshes) {
      if (loaded) this.drawInstances(loaded.mesh, loaded.instances);
    }
    const spheres = this.hands;
    spheres.clear();
    const scene = this.scene.sphere;
    spheres.data = spheres.data.length >= scene.data.length ? spheres.data
      : new Float32Array(scene.data.length);
    spheres.data.set(scene.data.subarray(0, STRIDE * scene.count));
    spheres.count = scene.count;
    const I = [1, 0, 0, 0, 1, 0, 0, 0, 1];
    for (const [x, y, z, r] of points) spheres.push(I, [x, y, z], [r, r, r], HAND_COLOUR);
    this.drawInstances(this.meshes.sphere, spheres);
    gl.bindVertexArray(null);
  }
}

// A column-major perspective projection and look-at view, for the page's own preview.
export function perspective(fovyRad, aspect, near, far) {
  const f = 1 / Math.tan(fovyRad / 2), nf = 1 / (near - far);
  return new Float32Array([f / aspect, 0, 0, 0, 0, f, 0, 0, 0, 0, (far + near) * nf, -1,
    0, 0, 2 * far * near * nf, 0]);
}

export function lookAt(eye, target, up) {
  const sub = (a, b) => [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
  const norm = (a) => { const l = Math.hypot(...a); return [a[0] / l, a[1] / l, a[2] / l]; };
  const cross = (a, b) => [a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2],
    a[0] * b[1] - a[1] * b[0]];
  const dot = (a, b) => a[0] * b[0] + a[1] * b[1] + a[2] * b[2];
  const z = norm(sub(eye, target)), x = norm(cross(up, z)), y = cross(z, x);
  return new Float32Array([x[0], y[0], z[0], 0, x[1], y[1], z[1], 0, x[2], y[2], z[2], 0,
    -dot(x, eye), -dot(y, eye), -dot(z, eye), 1]);
}
