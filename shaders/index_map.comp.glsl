#version 430
// The fusion index map by scatter: each surfel lands on the one pixel whose centre is nearest
// its projection; the nearest surfel of a pixel wins, the lowest index among equal depths.
// Pass 0 keeps each pixel's nearest depth, pass 1 the lowest index at that depth. Keys are
// stored inverted (atomicMax), so that the all-zero clear means empty.
layout(local_size_x = 64) in;
layout(std430, binding = 0) readonly buffer Positions { float pos[]; };   // camera frame, xyz
layout(std430, binding = 1) buffer Depth { uint depth_key[]; };
layout(std430, binding = 2) buffer Index { uint index_key[]; };

uniform vec4 u_K;          // fx, fy, cx, cy of the (supersampled) grid, OpenCV convention
uniform ivec2 u_size;      // grid width, height in pixels
uniform vec2 u_near_far;   // metres
uniform uint u_count;
uniform int u_pass;

void main() {
    // Groups are dispatched on a 2-D grid (a dimension holds at most 65535 of them).
    uint i = (gl_WorkGroupID.y * gl_NumWorkGroups.x + gl_WorkGroupID.x) * gl_WorkGroupSize.x
        + gl_LocalInvocationID.x;
    if (i >= u_count) return;
    vec3 p = vec3(pos[3u * i], pos[3u * i + 1u], pos[3u * i + 2u]);
    // The negated test also rejects NaN depths.
    if (!(p.z > u_near_far.x && p.z < u_near_far.y)) return;
    vec2 pix = floor(u_K.xy * p.xy / p.z + u_K.zw + 0.5);
    if (!(pix.x >= 0.0 && pix.y >= 0.0 && pix.x < float(u_size.x) && pix.y < float(u_size.y))) return;
    uint k = uint(pix.y) * uint(u_size.x) + uint(pix.x);
    uint key = ~floatBitsToUint(p.z);      // positive floats order as their bits
    if (u_pass == 0) atomicMax(depth_key[k], key);
    else if (depth_key[k] == key) atomicMax(index_key[k], ~i);
}
