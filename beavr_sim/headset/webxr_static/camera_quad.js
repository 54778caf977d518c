// The streamed camera panels inside the scene: each camera's newest image as a textured quad
// standing where its `camera` message says (docs/formats.md: `panel`, world frame, Z up),
// moved by the page's offset (panel_offset.js: the user's), facing the operator. Fed by the same `camera` messages as the page's overlay panel; a
// NO SIGNAL panel is the server's own image, and the quads are cleared when the connection
// drops, so a last image never stays up as if live.

import { linkProgram, worldToXr } from "./twin_gl.js";

const VERTEX_SHADER = `#version 300 es
layout(location = 0) in vec3 aPosition;
layout(location = 1) in vec2 aUv;
uniform mat4 uProjection;
uniform mat4 uView;
out vec2 vUv;
void main() {
  vUv = aUv;
  gl_Position = uProjection * uView * vec4(aPosition, 1.0);
}`;

const FRAGMENT_SHADER = `#version 300 es
precision mediump float;
uniform sampler2D uImage;
in vec2 vUv;
out vec4 outColor;
void main() {
  outColor = vec4(texture(uImage, vUv).rgb, 1.0);
}`;

function bytesOf(base64) {
  if (Uint8Array.fromBase64) return Uint8Array.fromBase64(base64);
  const binary = atob(base64);
  const bytes = new Uint8Array(binary.length);
  for (let i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes;
}

// The quad's four corners (XR position, then image uv) for a panel centred at `center` (world
// frame) moved by `offset`, `width` x `height` metres: facing the operator (world -x), the
// image's right along world -y.
export function quadVertices(center, width, height, offset) {
  const [x, y, z] = center.map((v, i) => v + offset[i]);
  const corner = (dy, dz, u, v) => [...worldToXr([x, y + dy, z + dz]), u, v];
  return new Float32Array([
    ...corner(width / 2, -height / 2, 0, 1), ...corner(-width / 2, -height / 2, 1, 1),
    ...corner(width / 2, height / 2, 0, 0), ...corner(-width / 2, height / 2, 1, 0),
  ]);
}

export class CameraQuads {
  // gl: the page's WebGL2 context (the twin's); offset: a PanelOffset (the user's move).
  constructor(gl, offset) {
    this.offset = offset;
    this.gl = gl;
    const program = linkProgram(gl, VERTEX_SHADER, FRAGMENT_SHADER, "camera quad");
    this.program = program;
    this.uProjection = gl.getUniformLocation(program, "uProjection");
    this.uView = gl.getUniformLocation(program, "uView");
    this.uImage = gl.getUniformLocation(program, "uImage");
    // name -> { vao, buffer, texture, ready, decoding, pending, key }
    this.quads = new Map();
    this.shown = 0;
    // Called after a new image is in a texture (the page's preview redraws).
    this.onShown = null;
  }

  // A `camera` message: its image decoded off the frame loop (createImageBitmap); while one
  // decodes, only the newest message waits (older ones are dropped, never queued).
  update(msg) {
    if (typeof msg.name !== "string" || typeof msg.jpeg !== "string" || !msg.panel) return;
    let quad = this.quads.get(msg.name);
    if (!quad) {
      quad = this.create();
      this.quads.set(msg.name, quad);
    }
    if (quad.decoding) {
      quad.pending = msg;
      return;
    }
    this.decode(quad, msg);
  }

  decode(quad, msg) {
    quad.decoding = true;
    const blob = new Blob([bytesOf(msg.jpeg)], { type: "image/jpeg" });
    createImageBitmap(blob).then((bitmap) => {
      if (this.quads.get(msg.name) === quad) this.upload(quad, msg, bitmap);
      bitmap.close();
    }).catch((err) => {
      console.warn(`camera ${msg.name}: image not decoded: ${err.message || err}`);
    }).finally(() => {
      quad.decoding = false;
      const next = quad.pending;
      quad.pending = null;
      if (next && this.quads.get(next.name) === quad) this.decode(quad, next);
    });
  }

  create() {
    const gl = this.gl;
    const vao = gl.createVertexArray();
    const buffer = gl.createBuffer();
    gl.bindVertexArray(vao);
    gl.bindBuffer(gl.ARRAY_BUFFER, buffer);
    gl.bufferData(gl.ARRAY_BUFFER, 4 * 5 * 4, gl.DYNAMIC_DRAW);
    gl.enableVertexAttribArray(0);
    gl.vertexAttribPointer(0, 3, gl.FLOAT, false, 20, 0);
    gl.enableVertexAttribArray(1);
    gl.vertexAttribPointer(1, 2, gl.FLOAT, false, 20, 12);
    gl.bindVertexArray(null);
    const texture = gl.createTexture();
    gl.bindTexture(gl.TEXTURE_2D, texture);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MIN_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_MAG_FILTER, gl.LINEAR);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_S, gl.CLAMP_TO_EDGE);
    gl.texParameteri(gl.TEXTURE_2D, gl.TEXTURE_WRAP_T, gl.CLAMP_TO_EDGE);
    return { vao, buffer, texture, ready: false, decoding: false, pending: null, key: "",
      place: null };
  }

  // The image into the quad's texture, and the quad where the message places it (its height
  // from the image's aspect).
  upload(quad, msg, bitmap) {
    const gl = this.gl;
    gl.bindTexture(gl.TEXTURE_2D, quad.texture);
    gl.texImage2D(gl.TEXTURE_2D, 0, gl.RGB, gl.RGB, gl.UNSIGNED_BYTE, bitmap);
    const w = Number(msg.panel.width_m) || 0.5;
    quad.place = { center: msg.panel.center.map(Number), w,
      h: w * bitmap.height / Math.max(bitmap.width, 1) };
    this.layout(quad);
    quad.ready = true;
    this.shown++;
    if (this.onShown) this.onShown();
  }

  // The quad's corners from its place and the offset (only when either changed).
  layout(quad) {
    const { center, w, h } = quad.place;
    const offset = this.offset ? this.offset.value : [0, 0, 0];
    const key = `${center},${w},${h},${offset}`;
    if (key === quad.key) return;
    const gl = this.gl;
    gl.bindBuffer(gl.ARRAY_BUFFER, quad.buffer);
    gl.bufferSubData(gl.ARRAY_BUFFER, 0, quadVertices(center, w, h, offset));
    quad.key = key;
  }

  // Every quad moved to the offset's new value (the user stepped it).
  relayout() {
    for (const quad of this.quads.values()) if (quad.place) this.layout(quad);
  }

  // Every quad gone (the connection dropped: nothing is streamed any more).
  clear() {
    const gl = this.gl;
    for (const quad of this.quads.values()) {
      gl.deleteVertexArray(quad.vao);
      gl.deleteBuffer(quad.buffer);
      gl.deleteTexture(quad.texture);
    }
    this.quads.clear();
  }

  // projection, view: column-major 4x4, as TwinRenderer.draw takes them.
  draw(projection, view) {
    if (!this.quads.size) return;
    const gl = this.gl;
    gl.useProgram(this.program);
    gl.enable(gl.DEPTH_TEST);
    gl.uniformMatrix4fv(this.uProjection, false, projection);
    gl.uniformMatrix4fv(this.uView, false, view);
    gl.activeTexture(gl.TEXTURE0);
    gl.uniform1i(this.uImage, 0);
    for (const quad of this.quads.values()) {
      if (!quad.ready) continue;
      gl.bindTexture(gl.TEXTURE_2D, quad.texture);
      gl.bindVertexArray(quad.vao);
      gl.drawArrays(gl.TRIANGLE_STRIP, 0, 4);
    }
    gl.bindVertexArray(null);
  }
}
