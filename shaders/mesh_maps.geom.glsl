#version 330
// Passes each triangle on with its three corner ids and positions (flat), so the fragment
// shader can pick the corner nearest to the pixel's surface point.
layout(triangles) in;
layout(triangle_strip, max_vertices = 3) out;

uniform vec4 u_K;          // fx, fy, cx, cy, OpenCV convention
uniform vec2 u_size;       // image width, height in pixels
uniform vec2 u_near_far;   // metres

in vec3 g_position[];
in vec3 g_normal[];
flat in int g_index[];

out vec3 f_position;       // perspective-correct: the pixel ray's hit on the triangle
out vec3 f_normal;
flat out ivec3 f_corner_index;
flat out vec3 f_corner0;
flat out vec3 f_corner1;
flat out vec3 f_corner2;

// Clip coordinates with w = z, so GL's perspective divide gives u = fx x/z + cx. Image pixel u
// covers window x in [u, u+1) (its centre u + 0.5 is GL's sample point); image row v goes to GL
// row v, and reading rows back bottom-up yields row 0 = top image row.
vec4 project(vec3 p) {
    float n = u_near_far.x;
    float f = u_near_far.y;
    float z = p.z;
    return vec4(2.0 * (u_K.x * p.x + (u_K.z + 0.5) * z) / u_size.x - z,
                2.0 * (u_K.y * p.y + (u_K.w + 0.5) * z) / u_size.y - z,
                ((f + n) * z - 2.0 * f * n) / (f - n),
                z);
}

void main() {
    for (int i = 0; i < 3; ++i) {
        if (any(isnan(g_position[i])) || any(isinf(g_position[i]))) {
            return;
        }
    }
    for (int i = 0; i < 3; ++i) {
        gl_Position = project(g_position[i]);
        f_position = g_position[i];
        f_normal = g_normal[i];
        f_corner_index = ivec3(g_index[0], g_index[1], g_index[2]);
        f_corner0 = g_position[0];
        f_corner1 = g_position[1];
        f_corner2 = g_position[2];
        EmitVertex();
    }
    EndPrimitive();
}
