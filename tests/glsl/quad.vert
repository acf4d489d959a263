#version 300 es
// Fullscreen quad for the SSILVB parity test: fragUV = 0..1 across the viewport (GL bottom-left origin).
in vec2 in_vert;
out vec2 fragUV;
void main() {
    fragUV = in_vert * 0.5 + 0.5;
    gl_Position = vec4(in_vert, 0.0, 1.0);
}
