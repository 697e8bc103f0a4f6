#version 330
// Surfels as unsized points: each lands on the one pixel whose centre is nearest its projection.
uniform vec4 u_K;          // fx, fy, cx, cy of the (supersampled) grid, OpenCV convention
uniform vec2 u_size;       // grid width, height in pixels
uniform vec2 u_near_far;   // metres

in vec3 in_position;       // camera frame

flat out int v_index;

void main() {
    v_index = gl_VertexID;
    float z = in_position.z;
    // The negated test also rejects NaN depths; (2, 2, 2) is outside the clip volume.
    if (!(z > u_near_far.x && z < u_near_far.y)) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
        return;
    }
    vec2 uv = u_K.xy * in_position.xy / z + u_K.zw;
    // Snap to the pixel centre here so the rasteriser's sub-pixel snapping cannot move a point.
    vec2 pix = floor(uv + 0.5);
    if (any(isnan(pix)) || any(isinf(pix))) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);
        return;
    }
    // Image row v goes to GL row v (no flip here): reading rows back bottom-up then yields
    // row 0 = top image row.
    vec2 ndc = (pix + 0.5) / u_size * 2.0 - 1.0;
    float zn = 2.0 * (z - u_near_far.x) / (u_near_far.y - u_near_far.x) - 1.0;
    gl_Position = vec4(ndc, zn, 1.0);
}
