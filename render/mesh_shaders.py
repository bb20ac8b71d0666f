"""GLSL 3.30 core shaders of the mesh rasterizer (``render.mesh_gl``).

One pass writes three float targets: colour (Lambert + ambient over the albedo), camera-space normal and
camera depth, and the triangle id (``gl_PrimitiveID + 1``, 0 where nothing is drawn). The vertex shader
takes OpenCV world-to-camera ``u_view`` and turns the camera into OpenGL eye space itself (y and z negated)
before ``u_proj`` (``toolkit.cameras.opengl_projection``).
"""

MESH_VERTEX = """
#version 330 core
uniform mat4 u_view;   // OpenCV world-to-camera
uniform mat4 u_proj;   // OpenGL clip-from-eye (toolkit.cameras.opengl_projection)
in vec3 in_pos;
in vec3 in_nrm;
in vec3 in_col;
in vec2 in_uv;
out vec3 v_cam;
out vec3 v_nrm;
out vec3 v_col;
out vec2 v_uv;
void main() {
    vec4 cam = u_view * vec4(in_pos, 1.0);
    v_cam = cam.xyz;
    v_nrm = mat3(u_view) * in_nrm;
    v_col = in_col;
    v_uv = in_uv;
    // OpenGL eye space is the OpenCV camera with y and z negated.
    gl_Position = u_proj * vec4(cam.x, -cam.y, -cam.z, 1.0);
}
"""

MESH_FRAGMENT = """
#version 330 core
uniform vec3 u_light;      // camera-space unit direction from the surface towards the light
uniform float u_ambient;
uniform bool u_use_tex;
uniform sampler2D u_tex;
in vec3 v_cam;
in vec3 v_nrm;
in vec3 v_col;
in vec2 v_uv;
layout(location = 0) out vec4 f_rgb;
layout(location = 1) out vec4 f_nrm_depth;
layout(location = 2) out vec4 f_id;
void main() {
    vec3 n = v_nrm / max(length(v_nrm), 1e-20);
    vec3 albedo = u_use_tex ? texture(u_tex, v_uv).rgb : v_col;
    float lambert = max(dot(n, u_light), 0.0);
    f_rgb = vec4(albedo * (u_ambient + (1.0 - u_ambient) * lambert), 1.0);
    f_nrm_depth = vec4(n, v_cam.z);
    f_id = vec4(float(gl_PrimitiveID + 1), 0.0, 0.0, 1.0);
}
"""
