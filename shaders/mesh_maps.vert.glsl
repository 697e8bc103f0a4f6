#version 330
// Mesh vertices in the camera frame; projection happens in the geometry shader.
in vec3 in_position;
in vec3 in_normal;

out vec3 g_position;
out vec3 g_normal;
flat out int g_index;

void main() {
    g_position = in_position;
    g_normal = in_normal;
    g_index = gl_VertexID;   // with an element buffer: the vertex's index in the full array
}
