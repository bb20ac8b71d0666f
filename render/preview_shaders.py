"""GLSL 3.30 core shaders of the preview splatter (``render.preview``); no SSBOs, so it runs on macOS too.

Per-Gaussian data live in an RGBA32F texture, ``TEXELS_PER_GAUSSIAN`` texels per Gaussian and
``GAUSSIANS_PER_ROW`` Gaussians per texture row:

- texel 0: mean xyz, opacity
- texel 1: world covariance xx, xy, xz, yy
- texel 2: world covariance yz, zz, r_cut (Mahalanobis radius where alpha reaches 1/255), unused
- texel 3: colour rgb, unused

Each drawn instance is one Gaussian (its id comes from a per-instance index buffer in back-to-front
order) and one 4-vertex triangle strip: a quad along the screen-space ellipse's principal axes, cut where
``opacity * exp(-sigma) = 1/255``. Window coordinates equal image coordinates (u, v) = (j + 0.5, i + 0.5):
NDC y = 2 v / H - 1 as in ``toolkit.cameras.opengl_projection``, so a read-back needs no flip.
"""

GAUSSIANS_PER_ROW = 1024
TEXELS_PER_GAUSSIAN = 4
TEXTURE_WIDTH = GAUSSIANS_PER_ROW * TEXELS_PER_GAUSSIAN

SPLAT_VERTEX = """
#version 330 core
uniform sampler2D u_data;
uniform vec3 u_rot0;      // rows of the world-to-camera rotation
uniform vec3 u_rot1;
uniform vec3 u_rot2;
uniform vec3 u_trans;
uniform vec4 u_intr;      // fx, fy, cx, cy (pixels)
uniform float u_skew;     // K[0, 1]: in the mean, not in the Jacobian (as gsplat)
uniform vec2 u_size;      // width, height
uniform vec2 u_clip;      // near, far
uniform vec4 u_lim;       // tangent clamp: -x, +x, -y, +y limits of x/z and y/z
uniform float u_eps2d;
in int a_id;
flat out vec2 v_mean;
flat out vec3 v_conic;
flat out float v_opacity;
flat out vec3 v_color;
flat out float v_cut;

void cull() {
    gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // all four corners equal: a zero-area strip
    v_mean = vec2(0.0); v_conic = vec3(0.0); v_opacity = 0.0; v_color = vec3(0.0); v_cut = -1.0;
}

void main() {
    int row = a_id / GPR;
    int col = (a_id - row * GPR) * 4;
    vec4 t0 = texelFetch(u_data, ivec2(col, row), 0);
    vec4 t1 = texelFetch(u_data, ivec2(col + 1, row), 0);
    vec4 t2 = texelFetch(u_data, ivec2(col + 2, row), 0);
    vec4 t3 = texelFetch(u_data, ivec2(col + 3, row), 0);
    vec3 p = vec3(dot(u_rot0, t0.xyz), dot(u_rot1, t0.xyz), dot(u_rot2, t0.xyz)) + u_trans;
    float z = p.z;
    float r_cut = t2.z;
    if (z <= u_clip.x || z >= u_clip.y || r_cut <= 0.0) { cull(); return; }
    // Camera covariance W Sigma W^T (mat3 takes columns; Sigma is symmetric).
    mat3 S = mat3(t1.x, t1.y, t1.z, t1.y, t1.w, t2.x, t1.z, t2.x, t2.y);
    mat3 W = transpose(mat3(u_rot0, u_rot1, u_rot2));
    mat3 C = W * S * transpose(W);
    // EWA Jacobian with gsplat's tangent clamp, so off-screen Gaussians do not blow up.
    float fx = u_intr.x, fy = u_intr.y;
    float tx = z * clamp(p.x / z, -u_lim.x, u_lim.y);
    float ty = z * clamp(p.y / z, -u_lim.z, u_lim.w);
    vec3 j0 = vec3(fx / z, 0.0, -fx * tx / (z * z));
    vec3 j1 = vec3(0.0, fy / z, -fy * ty / (z * z));
    float a = dot(j0, C * j0) + u_eps2d;
    float b = dot(j0, C * j1);
    float c = dot(j1, C * j1) + u_eps2d;
    float det = a * c - b * b;
    if (!(det > 0.0)) { cull(); return; }
    vec2 mean = vec2(fx * p.x / z + u_skew * p.y / z + u_intr.z, fy * p.y / z + u_intr.w);
    // Principal axes of the 2D covariance; the quad is the ellipse's bounding rectangle.
    float mid = 0.5 * (a + c);
    float l1 = mid + sqrt(max(mid * mid - det, 0.0));
    float l2 = det / l1;
    vec2 e1 = vec2(b, l1 - a);
    vec2 alt = vec2(l1 - c, b);
    if (dot(alt, alt) > dot(e1, e1)) e1 = alt;
    float n1 = length(e1);
    e1 = n1 > 0.0 ? e1 / n1 : (a >= c ? vec2(1.0, 0.0) : vec2(0.0, 1.0));
    vec2 e2 = vec2(-e1.y, e1.x);
    // A hair of margin so rounding never cuts a pixel whose alpha is just above 1/255.
    float h1 = min(r_cut * sqrt(l1) * 1.0001 + 0.01, 1e7);
    float h2 = min(r_cut * sqrt(l2) * 1.0001 + 0.01, 1e7);
    vec2 corner = vec2((gl_VertexID & 1) == 1 ? 1.0 : -1.0, (gl_VertexID & 2) == 2 ? 1.0 : -1.0);
    vec2 uv = mean + corner.x * h1 * e1 + corner.y * h2 * e2;
    gl_Position = vec4(2.0 * uv.x / u_size.x - 1.0, 2.0 * uv.y / u_size.y - 1.0, 0.0, 1.0);
    v_mean = mean;
    v_conic = vec3(c, -b, a) / det;
    v_opacity = t0.w;
    v_color = t3.xyz;
    v_cut = 0.5 * r_cut * r_cut * 1.0001 + 1e-6;  // ln(255 o), with a hair of slack for rounding
}
""".replace("GPR", str(GAUSSIANS_PER_ROW))

SPLAT_FRAGMENT = """
#version 330 core
flat in vec2 v_mean;
flat in vec3 v_conic;
flat in float v_opacity;
flat in vec3 v_color;
flat in float v_cut;
out vec4 frag;
void main() {
    vec2 d = v_mean - gl_FragCoord.xy;  // pixel centres sit at (j + 0.5, i + 0.5)
    float sigma = 0.5 * (v_conic.x * d.x * d.x + v_conic.z * d.y * d.y) + v_conic.y * d.x * d.y;
    if (sigma < 0.0 || sigma > v_cut) discard;  // outside the alpha = 1/255 ellipse: skip the exp
    float alpha = min(0.99, v_opacity * exp(-sigma));
    if (alpha < 1.0 / 255.0) discard;
    frag = vec4(v_color * alpha, alpha);  // premultiplied; blended with (ONE, ONE_MINUS_SRC_ALPHA)
}
"""

FULLSCREEN_VERTEX = """
#version 330 core
void main() {
    vec2 p = vec2((gl_VertexID == 1) ? 3.0 : -1.0, (gl_VertexID == 2) ? 3.0 : -1.0);
    gl_Position = vec4(p, 0.0, 1.0);
}
"""

# Copies (blending off) or composites "over" (blending on) a cached premultiplied layer, texel for texel.
LAYER_FRAGMENT = """
#version 330 core
uniform sampler2D u_layer;
out vec4 frag;
void main() { frag = texelFetch(u_layer, ivec2(gl_FragCoord.xy), 0); }
"""

# Shows the premultiplied frame over a background in a window (image row 0 at the window's top).
PRESENT_FRAGMENT = """
#version 330 core
uniform sampler2D u_frame;
uniform vec3 u_background;
uniform vec2 u_scale;       // frame pixels per window pixel
uniform float u_win_height;
uniform vec4 u_rect;        // overlay rectangle x0, y0, x1, y1 in image pixels (x1 < x0: none)
out vec4 frag;
void main() {
    vec2 img = vec2(gl_FragCoord.x, u_win_height - gl_FragCoord.y) * u_scale;
    vec4 c = texelFetch(u_frame, ivec2(img), 0);
    vec3 rgb = c.rgb + (1.0 - c.a) * u_background;
    bool inside = img.x >= u_rect.x && img.x <= u_rect.z && img.y >= u_rect.y && img.y <= u_rect.w;
    bool edge = inside && (img.x < u_rect.x + 2.0 || img.x > u_rect.z - 2.0 || img.y < u_rect.y + 2.0 || img.y > u_rect.w - 2.0);
    frag = vec4(edge ? vec3(1.0, 0.2, 0.1) : clamp(rgb, 0.0, 1.0), 1.0);
}
"""
