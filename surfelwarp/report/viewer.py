"""One self-contained HTML page (view.html) to scrub through a run's saved live frames as
points in 3-D: it opens from disk with no server and no network, so it carries its own WebGL
code and the points themselves (base64 float32 positions and uint8 colours)."""
from __future__ import annotations

import base64
import html
import json
import re
from pathlib import Path
from string import Template

import numpy as np

from surfelwarp.errors import InputError
from surfelwarp.io.ply import read_ply, write_atomic

# The camera frame is OpenCV's (y down, z forward); the page's is y up, z toward the viewer.
TO_VIEWER = np.array([1.0, -1.0, -1.0], np.float32)

# Everything read_ply (or a table without the contract's fields) can raise for a damaged file.
DAMAGED = (ValueError, KeyError, OSError, TypeError, IndexError, AttributeError)


def live_frames(out_dir: Path) -> list[tuple[int, Path]]:
    frames = []
    for path in (out_dir / "live").glob("frame-*.ply"):
        match = re.fullmatch(r"frame-(\d+)\.ply", path.name)
        if match:
            frames.append((int(match.group(1)), path))
    if not frames:
        raise InputError(out_dir, "no live frames (live/frame-NNNNNN.ply) to view")
    return sorted(frames)


def method_name(out_dir: Path) -> str:
    # A folder of PLYs without metrics.json is still worth viewing: name it after the folder.
    path = out_dir / "metrics.json"
    if not path.is_file():
        return out_dir.name
    try:
        return str(json.loads(path.read_text()).get("method", out_dir.name))
    except (ValueError, OSError, AttributeError):
        raise InputError(path, "not a readable metrics.json") from None


def load(path: Path, share: tuple[int, int], seed: int) -> tuple[int, np.ndarray, np.ndarray]:
    """The PLY's point count, and share[0]/share[1] of its points (rounded down, chosen at random
    but the same every time, in file order) dropping non-finite ones: (N, 3) float32 positions in
    the viewer's frame and (N, 3) uint8 RGB, the fused colour or else the renders' normal colour."""
    try:
        table, _ = read_ply(path)
        count = len(table)
        keep = min(count, count * share[0] // share[1])     # in integers: the sum cannot overshoot
        table = table[np.sort(np.random.default_rng(seed).permutation(count)[:keep])]
        stack = lambda *fields: np.stack([table[f] for f in fields], -1).astype(np.float32)  # noqa: E731
        with np.errstate(all="ignore"):     # a damaged file's inf and NaN are dropped below
            points = stack("x", "y", "z") * TO_VIEWER
            if {"red", "green", "blue"} <= set(table.dtype.names):
                colours = stack("red", "green", "blue").astype(np.uint8)
            else:
                normals = stack("nx", "ny", "nz") * TO_VIEWER
                normals /= np.maximum(np.linalg.norm(normals, axis=1, keepdims=True), 1e-12)
                colours = np.clip(np.rint(127.5 + 127.5 * np.nan_to_num(normals)), 0, 255).astype(np.uint8)
    except DAMAGED as exc:
        raise InputError(path, f"damaged PLY ({exc.__class__.__name__}: {exc})".splitlines()[0]) from None
    finite = np.isfinite(points).all(axis=1)
    return count, points[finite].astype("<f4"), colours[finite]


def encode(array: np.ndarray) -> str:
    return base64.b64encode(np.ascontiguousarray(array).tobytes()).decode("ascii")


def frame_data(out_dir: Path, max_points: int) -> tuple[list[dict], int, np.ndarray, np.ndarray]:
    """Per-frame embedded records, the points in the files, and the box around those shown."""
    frames = live_frames(out_dir)
    # A first pass only counts, so no more than max_points are ever held at once.
    total = sum(load(path, (0, 1), frame)[0] for frame, path in frames)
    records, lo, hi = [], np.full(3, np.inf), np.full(3, -np.inf)
    for frame, path in frames:
        _, points, colours = load(path, (min(max_points, total), max(total, 1)), seed=frame)
        lo, hi = np.vstack([lo, points]).min(0), np.vstack([hi, points]).max(0)
        records.append({"frame": frame, "shown": len(points), "positions": encode(points), "colours": encode(colours)})
    return records, total, lo, hi


def write_viewer(out_dir: Path, html_path: Path | None = None, max_points: int = 150_000) -> Path:
    """Write the viewer of OUT's live frames (default OUT/view.html), at most `max_points` points
    over all frames, each frame uniformly subsampled; returns the page's path."""
    out_dir = Path(out_dir)
    if max_points < 1:
        raise ValueError(f"max_points must be at least 1, not {max_points}")
    html_path = out_dir / "view.html" if html_path is None else Path(html_path)
    records, total, lo, hi = frame_data(out_dir, max_points)
    shown = sum(r["shown"] for r in records)
    if not np.isfinite(lo).all():      # nothing to show: any box will do
        lo, hi = np.zeros(3), np.zeros(3)
    data = {"centre": [float(v) for v in (lo + hi) / 2],
            "radius": max(float(np.linalg.norm(hi - lo)) / 2, 1e-3), "frames": records}
    page = PAGE.substitute(method=html.escape(method_name(out_dir)), shown=f"{shown:,}", total=f"{total:,}",
                           frames=len(records), data=json.dumps(data, separators=(",", ":")))
    write_atomic(html_path, page.encode("utf-8"))
    return html_path


# The page: string.Template fills $names, so the script below must not use a dollar sign.
PAGE = Template("""<!DOCTYPE html>
<html lang="en"><head><meta charset="utf-8"><title>$method: live frames</title>
<style>
html, body { margin: 0; height: 100%; overflow: hidden; background: #1e1e1e; color: #ddd; font: 13px sans-serif; }
canvas { display: block; width: 100%; height: 100%; cursor: grab; }
#panel { position: absolute; left: 10px; top: 10px; padding: 8px 10px; background: rgba(0,0,0,0.55); }
#panel input { width: 260px; vertical-align: middle; }
</style></head>
<body><canvas id="view"></canvas><div id="panel">
<div><b>$method</b>: $frames live frames, showing $shown of $total points (uniform subsample)</div>
<div><input id="slider" type="range" min="0" max="0" step="1" value="0"> <span id="label"></span></div>
<div id="hint">drag to orbit, wheel to zoom</div></div>
<script id="frames" type="application/json">$data</script>
<script>
"use strict";
var data = JSON.parse(document.getElementById("frames").textContent);
var canvas = document.getElementById("view");
var slider = document.getElementById("slider");
var label = document.getElementById("label");
// The buffer must survive compositing so a headless --screenshot sees the drawn points.
var gl = canvas.getContext("webgl", {preserveDrawingBuffer: true, antialias: false});

function bytesOf(text) {
  var binary = atob(text), bytes = new Uint8Array(binary.length);
  for (var i = 0; i < binary.length; i++) bytes[i] = binary.charCodeAt(i);
  return bytes;
}

function compile(type, source) {
  var shader = gl.createShader(type);
  gl.shaderSource(shader, source);
  gl.compileShader(shader);
  if (!gl.getShaderParameter(shader, gl.COMPILE_STATUS)) throw new Error(gl.getShaderInfoLog(shader));
  return shader;
}

// Column-major 4x4 matrices, as uniformMatrix4fv takes them.
function multiply(a, b) {
  var out = new Float32Array(16);
  for (var i = 0; i < 16; i++)
    for (var k = 0; k < 4; k++) out[i] += a[k * 4 + i % 4] * b[i - i % 4 + k];
  return out;
}
function translation(x, y, z) { return new Float32Array([1,0,0,0, 0,1,0,0, 0,0,1,0, x,y,z,1]); }
function rotationX(a) {
  var c = Math.cos(a), s = Math.sin(a); return new Float32Array([1,0,0,0, 0,c,s,0, 0,-s,c,0, 0,0,0,1]); }
function rotationY(a) {
  var c = Math.cos(a), s = Math.sin(a); return new Float32Array([c,0,-s,0, 0,1,0,0, s,0,c,0, 0,0,0,1]); }
function perspective(fovy, aspect, near, far) {
  var f = 1 / Math.tan(fovy / 2), d = near - far;
  return new Float32Array([f / aspect,0,0,0, 0,f,0,0, 0,0,(far + near) / d,-1, 0,0,2 * far * near / d,0]);
}

var centre = data.centre, radius = data.radius;
// Start where the input camera was: looking down -z at the points (yaw and pitch 0).
var yaw = 0, pitch = 0, distance = 2.5 * radius, current = 0, program = null, buffers = [];

function setup() {
  program = gl.createProgram();
  gl.attachShader(program, compile(gl.VERTEX_SHADER,
    "attribute vec3 position; attribute vec3 colour; uniform mat4 transform; uniform float size;" +
    "varying vec3 tint; void main() { gl_Position = transform * vec4(position, 1.0);" +
    " gl_PointSize = size; tint = colour; }"));
  gl.attachShader(program, compile(gl.FRAGMENT_SHADER,
    "precision mediump float; varying vec3 tint; void main() { gl_FragColor = vec4(tint, 1.0); }"));
  gl.linkProgram(program);
  if (!gl.getProgramParameter(program, gl.LINK_STATUS)) throw new Error(gl.getProgramInfoLog(program));
  buffers = data.frames.map(function (f) {
    var positions = gl.createBuffer(), colours = gl.createBuffer();
    gl.bindBuffer(gl.ARRAY_BUFFER, positions);
    gl.bufferData(gl.ARRAY_BUFFER, new Float32Array(bytesOf(f.positions).buffer), gl.STATIC_DRAW);
    gl.bindBuffer(gl.ARRAY_BUFFER, colours);
    gl.bufferData(gl.ARRAY_BUFFER, bytesOf(f.colours), gl.STATIC_DRAW);
    return {positions: positions, colours: colours, count: f.shown};
  });
  gl.enable(gl.DEPTH_TEST);
}

function draw() {
  var scale = window.devicePixelRatio || 1;
  var width = Math.max(1, Math.round(canvas.clientWidth * scale));
  var height = Math.max(1, Math.round(canvas.clientHeight * scale));
  if (canvas.width !== width || canvas.height !== height) { canvas.width = width; canvas.height = height; }
  gl.viewport(0, 0, width, height);
  gl.clearColor(0.118, 0.118, 0.118, 1);
  gl.clear(gl.COLOR_BUFFER_BIT | gl.DEPTH_BUFFER_BIT);
  var frame = buffers[current];
  if (!frame || frame.count === 0) return;
  var view = multiply(translation(0, 0, -distance), multiply(rotationX(pitch),
    multiply(rotationY(yaw), translation(-centre[0], -centre[1], -centre[2]))));
  var projection = perspective(Math.PI / 4, width / height, distance / 100, distance + 4 * radius);
  gl.useProgram(program);
  gl.uniformMatrix4fv(gl.getUniformLocation(program, "transform"), false, multiply(projection, view));
  gl.uniform1f(gl.getUniformLocation(program, "size"), 2 * scale);
  var position = gl.getAttribLocation(program, "position"), colour = gl.getAttribLocation(program, "colour");
  gl.bindBuffer(gl.ARRAY_BUFFER, frame.positions);
  gl.enableVertexAttribArray(position);
  gl.vertexAttribPointer(position, 3, gl.FLOAT, false, 0, 0);
  gl.bindBuffer(gl.ARRAY_BUFFER, frame.colours);
  gl.enableVertexAttribArray(colour);
  gl.vertexAttribPointer(colour, 3, gl.UNSIGNED_BYTE, true, 0, 0);
  gl.drawArrays(gl.POINTS, 0, frame.count);
}

function show(index) {
  current = index;
  var f = data.frames[index];
  label.textContent = "frame " + f.frame + " (" + f.shown.toLocaleString() + " points)";
  if (program) draw();
}

slider.max = String(data.frames.length - 1);
slider.addEventListener("input", function () { show(Number(slider.value)); });
var dragging = null;
canvas.addEventListener("mousedown", function (e) { dragging = [e.clientX, e.clientY]; });
window.addEventListener("mouseup", function () { dragging = null; });
window.addEventListener("mousemove", function (e) {
  if (!dragging) return;
  yaw += 0.01 * (e.clientX - dragging[0]);
  pitch = Math.max(-1.55, Math.min(1.55, pitch + 0.01 * (e.clientY - dragging[1])));
  dragging = [e.clientX, e.clientY];
  draw();
});
canvas.addEventListener("wheel", function (e) {
  e.preventDefault();
  distance = Math.max(0.05 * radius, Math.min(50 * radius, distance * Math.exp(0.001 * e.deltaY)));
  draw();
}, {passive: false});
window.addEventListener("resize", function () { if (program) draw(); });

if (gl) setup();
else document.getElementById("hint").textContent = "this browser has no WebGL: nothing can be drawn";
// Drawn now, not on a later animation frame, so the page is complete when its load event fires.
show(0);
</script>
</body></html>
""")
