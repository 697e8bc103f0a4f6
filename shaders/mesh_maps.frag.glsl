#version 330
in vec3 f_position;
in vec3 f_normal;
flat in ivec3 f_corner_index;
flat in vec3 f_corner0;
flat in vec3 f_corner1;
flat in vec3 f_corner2;

layout(location = 0) out int o_index;     // vertex index + 1, so the cleared value 0 means empty
layout(location = 1) out vec4 o_vertex;
layout(location = 2) out vec4 o_normal;

void main() {
    vec3 d = vec3(dot(f_position - f_corner0, f_position - f_corner0),
                  dot(f_position - f_corner1, f_position - f_corner1),
                  dot(f_position - f_corner2, f_position - f_corner2));
    int nearest = d.x <= d.y ? (d.x <= d.z ? 0 : 2) : (d.y <= d.z ? 1 : 2);
    o_index = f_corner_index[nearest] + 1;
    o_vertex = vec4(f_position, 1.0);
    float len = length(f_normal);
    o_normal = vec4(len > 0.0 ? f_normal / len : vec3(0.0), 0.0);
}
