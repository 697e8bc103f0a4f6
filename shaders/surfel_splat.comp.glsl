#version 430
// Solver maps by scatter: each surfel is an opaque disk; every pixel whose ray meets the disk
// takes the surfel whose intersection is nearest, the lowest index among equal depths. The
// pixels tried are those whose centres lie in the projection of the disk's bounding box.
// Pass 0 keeps each pixel's nearest depth key, pass 1 the lowest index at that key. Keys are
// inverted (atomicMax) so the all-zero clear means empty; the fill surfels' keys carry a
// lower top bit, so they only take pixels no surfel of the first set reached.
// Pass 0 also keeps each surfel's box of the pixels it can win (those whose key was at most its
// own when it wrote it: keys only grow), and pass 1 tries only those pixels.
layout(local_size_x = 64) in;
layout(std430, binding = 0) readonly buffer Positions { float pos[]; };    // camera frame, xyz
layout(std430, binding = 4) readonly buffer Normals { float nrm[]; };
layout(std430, binding = 5) readonly buffer Radii { float radius[]; };      // metres
layout(std430, binding = 1) buffer Depth { uint depth_key[]; };
layout(std430, binding = 2) buffer Index { uint index_key[]; };
layout(std430, binding = 3) readonly buffer Elements { uint element[]; };   // surfels drawn, in order
layout(std430, binding = 6) buffer Boxes { uint win_box[]; };   // per element: first, last pixel (u | v << 16)
// (so an image side is at most MAX_SIDE_PX, solver_maps.py)

uniform vec4 u_K;          // fx, fy, cx, cy, OpenCV convention
uniform ivec2 u_size;      // image width, height
uniform vec2 u_near_far;   // metres
uniform float u_max_size;  // largest square side tried, pixels
uniform float u_max_radius_px;   // a disk's radius is cut to this many pixels at its centre's depth (0: not)
uniform float u_min_cos;   // smallest |cos| between a pixel ray and a disk normal used in the division
uniform uint u_count;      // elements
uniform uint u_first_count;   // elements before this are the first set, the rest fill
uniform int u_pass;

void main() {
    // Groups are dispatched on a 2-D grid (a dimension holds at most 65535 of them).
    uint e = (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x
        + gl_LocalInvocationID.x;
    if (e >= u_count) return;
    uint i = element[e];
    vec3 p = vec3(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u]);
    vec3 n_in = vec3(nrm[3u * i], nrm[3u * i + 1u], nrm[3u * i + 2u]);
    float r = radius[i];
    if (u_max_radius_px > 0.0) r = min(r, u_max_radius_px * p.z / u_K.x);
    float len_n = length(n_in);
    vec3 n = n_in / len_n;
    vec3 ext = r * sqrt(max(vec3(1.0) - n * n, vec3(0.0)));     // the disk's extent along each axis
    // The negated tests also reject NaNs.
    if (!(r > 0.0) || !(len_n > 0.0) || !(p.z - ext.z > u_near_far.x && p.z + ext.z < u_near_far.y)) return;
    // The disk lies in its axis-aligned box, whose projection is bounded by its 8 corners'.
    vec2 lo = vec2(1e30);
    vec2 hi = vec2(-1e30);
    for (int c = 0; c < 8; ++c) {
        vec3 s = vec3((c & 1) == 0 ? -1.0 : 1.0, (c & 2) == 0 ? -1.0 : 1.0, (c & 4) == 0 ? -1.0 : 1.0);
        vec3 q = p + s * ext;
        vec2 uv = u_K.xy * q.xy / q.z + u_K.zw;
        lo = min(lo, uv);
        hi = max(hi, uv);
    }
    vec2 centre = 0.5 * (lo + hi);
    // 0.01 px on each side: a pixel centre on the box's edge stays inside despite rounding
    // (~1e-4 px). A margin of 1 px tried ~1.8x the pixels on disks 2 px across, all missed.
    vec2 half_size = min(0.5 * (hi - lo) + 0.01, vec2(0.5 * u_max_size));
    if (any(isnan(centre)) || any(isinf(centre)) || any(isnan(half_size))) return;
    // Clamped on both sides before the conversion to int (a float beyond int range converts
    // to anything).
    ivec2 first = ivec2(clamp(ceil(centre - half_size), vec2(0.0), vec2(u_size)));
    ivec2 last = ivec2(clamp(ceil(centre + half_size) - 1.0, vec2(-1.0), vec2(u_size - 1)));
    float ez = r * sqrt(max(1.0 - n.z * n.z, 0.0));
    uint layer = e < u_first_count ? 0x80000000u : 0u;
    if (u_pass == 1) {      // the same tests as in pass 0 led here
        uint a = win_box[2u * e], b = win_box[2u * e + 1u];
        first = max(first, ivec2(a & 0xFFFFu, a >> 16));
        last = min(last, ivec2(b & 0xFFFFu, b >> 16));
    }
    ivec2 win_first = ivec2(0x7FFF), win_last = ivec2(-1);
    for (int v = first.y; v <= last.y; ++v) {
        for (int u = first.x; u <= last.x; ++u) {
            vec3 d = vec3((vec2(u, v) - u_K.zw) / u_K.xy, 1.0);    // ray through the pixel centre
            float dn = dot(d, n);
            // Near-grazing rays would put the intersection anywhere along the ray: clamp the cosine.
            float min_dn = u_min_cos * length(d);
            if (abs(dn) < min_dn) dn = dn < 0.0 ? -min_dn : min_dn;
            float t = dot(p, n) / dn;                    // depth of the intersection (d.z = 1)
            vec3 q = t * d - p;
            if (!(t > 0.0) || dot(q, q) > r * r) continue;
            // No point of the disk is deeper or shallower than this, whatever the clamp did.
            float z = clamp(t, p.z - ez, p.z + ez);
            uint key = layer | (~floatBitsToUint(z) >> 1);
            uint k = uint(v) * uint(u_size.x) + uint(u);
            if (u_pass == 1) {
                if (depth_key[k] == key) atomicMax(index_key[k], ~i);
            } else if (atomicMax(depth_key[k], key) <= key) {
                win_first = min(win_first, ivec2(u, v));
                win_last = max(win_last, ivec2(u, v));
            }
        }
    }
    if (u_pass == 0) {      // an empty box (first > last) where it can win nothing
        win_box[2u * e] = uint(win_first.x) | (uint(win_first.y) << 16);
        win_box[2u * e + 1u] = uint(max(win_last.x, 0)) | (uint(max(win_last.y, 0)) << 16);
    }
}
