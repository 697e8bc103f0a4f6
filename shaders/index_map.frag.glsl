#version 330
flat in int v_index;
flat in vec4 v_vertex;     // xyz position, w confidence
flat in vec3 v_normal;

layout(location = 0) out int o_index;     // index + 1, so the cleared value 0 means empty
layout(location = 1) out vec4 o_vertex;
layout(location = 2) out vec4 o_normal;
layout(location = 3) out float o_confidence;

void main() {
    o_index = v_index + 1;
    o_vertex = vec4(v_vertex.xyz, 1.0);
    o_normal = vec4(v_normal, 0.0);
    o_confidence = v_vertex.w;
}
