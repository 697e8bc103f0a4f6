#version 330
// Linear camera depth z (perspective-correct, exact on a planar triangle) and the unit
// surface normal turned towards the camera; in a second target, the material point seen
// (interpolated rest position, w = 1 where a surface is drawn) for the texture.
in vec3 v_position;
in vec3 v_normal;
in vec3 v_material;
layout(location = 0) out vec4 out_depth_normal;
layout(location = 1) out vec4 out_material;

void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_position) > 0.0) n = -n;
    out_depth_normal = vec4(v_position.z, n);
    out_material = vec4(v_material, 1.0);
}
