#version 330
// Linear camera depth z (perspective-correct, exact on a planar triangle) and the unit
// surface normal turned towards the camera.
in vec3 v_position;
in vec3 v_normal;
out vec4 out_depth_normal;

void main() {
    vec3 n = normalize(v_normal);
    if (dot(n, v_position) > 0.0) n = -n;
    out_depth_normal = vec4(v_position.z, n);
}
