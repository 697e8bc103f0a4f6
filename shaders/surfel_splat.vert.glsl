#version 330
// Surfels as opaque disks: one point sprite per surfel, sized to cover the disk's projection; the
// fragment shader cuts the disk out by ray/disk intersection.
uniform vec4 u_K;          // fx, fy, cx, cy, OpenCV convention
uniform vec2 u_fb_size;    // framebuffer width, height (image plus a margin on every side)
uniform float u_margin;    // pixels of margin, so disks centred just off the image still draw
uniform vec2 u_near_far;   // metres
uniform float u_max_size;  // largest point size the driver draws

in vec3 in_position;       // camera frame
in vec3 in_normal;
in float in_radius;

flat out vec3 v_position;
flat out vec3 v_normal;   // as given (the fragment shader normalises its own copy)
flat out float v_radius;
flat out int v_index;

const vec4 OUTSIDE = vec4(2.0, 2.0, 2.0, 1.0);   // beyond the clip volume: dropped

void main() {
    vec3 p = in_position;
    float r = in_radius;
    float len_n = length(in_normal);
    vec3 n = in_normal / len_n;
    v_position = p;
    v_normal = in_normal;
    v_radius = r;
    v_index = gl_VertexID;   // with an element buffer this is the index into the full array
    // Extent of the disk along each camera axis.
    vec3 e = r * sqrt(max(vec3(1.0) - n * n, vec3(0.0)));
    // The negated tests also reject NaNs.
    if (!(r > 0.0) || !(len_n > 0.0) || !(p.z - e.z > u_near_far.x && p.z + e.z < u_near_far.y)) {
        gl_Position = OUTSIDE;
        return;
    }
    // The disk lies in its axis-aligned box, whose projection is bounded by its 8 corners' (all
    // in front of the camera here).
    vec2 lo = vec2(1e30);
    vec2 hi = vec2(-1e30);
    for (int i = 0; i < 8; ++i) {
        vec3 s = vec3((i & 1) == 0 ? -1.0 : 1.0, (i & 2) == 0 ? -1.0 : 1.0, (i & 4) == 0 ? -1.0 : 1.0);
        vec3 c = p + s * e;
        vec2 uv = u_K.xy * c.xy / c.z + u_K.zw;
        lo = min(lo, uv);
        hi = max(hi, uv);
    }
    // A pixel centre at image coordinate u sits at window coordinate u + 0.5 + margin; image row
    // v goes to GL row v (reading rows back bottom-up then gives row 0 = top image row).
    vec2 centre = 0.5 * (lo + hi) + 0.5 + u_margin;
    // +2: pixel centres within the box are strictly inside the sprite despite rounding.
    float size = max(hi.x - lo.x, hi.y - lo.y) + 2.0;
    if (any(isnan(centre)) || any(isinf(centre)) || isnan(size)) {
        gl_Position = OUTSIDE;
        return;
    }
    gl_PointSize = min(size, u_max_size);
    gl_Position = vec4(centre / u_fb_size * 2.0 - 1.0, 0.0, 1.0);
}
