#version 330
uniform vec4 u_K;
uniform float u_margin;
uniform vec2 u_near_far;
uniform vec2 u_depth_layer;   // (offset, scale) of this draw's depth range in [0, 1]: a later
                              // draw into a deeper layer only fills pixels left empty
uniform float u_min_cos;   // smallest |cos| between a pixel ray and a disk normal used in the division

flat in vec3 v_position;
flat in vec3 v_normal;
flat in float v_radius;
flat in int v_index;

layout(location = 0) out int o_index;    // index + 1, so the cleared value 0 means empty

void main() {
    vec2 uv = gl_FragCoord.xy - 0.5 - u_margin;
    vec3 d = vec3((uv - u_K.zw) / u_K.xy, 1.0);    // ray through the pixel centre, unit depth
    vec3 n = normalize(v_normal);
    vec3 p = v_position;
    float dn = dot(d, n);
    // Near-grazing rays would put the intersection anywhere along the ray: clamp the cosine.
    float min_dn = u_min_cos * length(d);
    if (abs(dn) < min_dn) dn = dn < 0.0 ? -min_dn : min_dn;
    float t = dot(p, n) / dn;                       // depth of the intersection (d.z = 1)
    vec3 q = t * d - p;
    if (!(t > 0.0) || dot(q, q) > v_radius * v_radius) discard;
    // No point of the disk is deeper or shallower than this, whatever the clamp did.
    float ez = v_radius * sqrt(max(1.0 - n.z * n.z, 0.0));
    float z = clamp(t, p.z - ez, p.z + ez);
    gl_FragDepth = u_depth_layer.x + u_depth_layer.y * (z - u_near_far.x) / (u_near_far.y - u_near_far.x);
    o_index = v_index + 1;
}
