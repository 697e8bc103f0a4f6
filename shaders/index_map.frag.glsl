#version 330
flat in int v_index;

layout(location = 0) out int o_index;     // index + 1, so the cleared value 0 means empty

void main() {
    o_index = v_index + 1;
}
