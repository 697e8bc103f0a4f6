#version 330
// Camera-frame vertices (OpenCV: x right, y down, z forward, metres) to clip space.
// Pixel u (centre of pixel u at integer u) covers NDC [2u/W - 1, 2(u+1)/W - 1]; rows are not
// flipped, so GL window row v holds image row v and glReadPixels returns the image top-down.
uniform vec4 intrinsics;   // fx, fy, cx, cy
uniform vec2 size;         // width, height in pixels
uniform vec2 clip_range;   // near, far in metres

in vec3 in_position;
in vec3 in_normal;
in vec3 in_material;    // the vertex's material point (rest position): the texture moves with it
out vec3 v_position;
out vec3 v_normal;
out vec3 v_material;

void main() {
    float z = in_position.z;
    float near = clip_range.x, far = clip_range.y;
    float x_clip = 2.0 * (intrinsics.x * in_position.x + (intrinsics.z + 0.5) * z) / size.x - z;
    float y_clip = 2.0 * (intrinsics.y * in_position.y + (intrinsics.w + 0.5) * z) / size.y - z;
    float z_clip = ((far + near) * z - 2.0 * far * near) / (far - near);
    gl_Position = vec4(x_clip, y_clip, z_clip, z);
    v_position = in_position;
    v_normal = in_normal;
    v_material = in_material;
}
